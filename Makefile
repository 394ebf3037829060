# Two set-up-free commands: `make demo` (the main job) and `make test`.
# Each creates .venv on first use and installs what it needs. On a machine that should not pull the
# multi-GB CUDA wheel, the CPU build is pinned; override with `make test TORCH=torch` (or any spec).
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
PY := $(VENV)/bin/python
STAMP := $(VENV)/.mssf-installed

.PHONY: demo quickstart test bench clean-venv

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install --quiet "$(TORCH)"
	$(PY) -m pip install --quiet -e ".[dev,examples]"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/train_demo.py

quickstart: $(STAMP)
	$(PY) examples/quickstart.py

test: $(STAMP)
	$(PY) -m pytest

# One target per benchmark script: `make bench-centroids`, `make bench-msdff`, `make bench-detectors`,
# `make bench-threads`, ... (any benchmarks/NAME.py, options in BENCH_ARGS); `make bench` runs them all.
# Durations: docs/performance.md ("Benchmark targets").
BENCHMARKS := $(patsubst benchmarks/%.py,%,$(filter-out benchmarks/_%,$(wildcard benchmarks/*.py)))
BENCH_ARGS ?=

bench: $(addprefix bench-,$(BENCHMARKS))

# (a pattern rule, not .PHONY: make skips implicit rules for phony targets)
bench-%: benchmarks/%.py $(STAMP)
	$(PY) $< $(BENCH_ARGS)

clean-venv:
	rm -rf $(VENV)
