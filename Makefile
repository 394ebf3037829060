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
	# The official VoD evaluation kit, for the oracle test only; --no-deps: its visualisation extras
	# (k3d, ...) are never used by vod.evaluation, which needs numba (in the dev extra) and numpy.
	$(PY) -m pip install --quiet --no-deps "vod-tudelft==1.0.3"
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/train_demo.py

quickstart: $(STAMP)
	$(PY) examples/quickstart.py

test: $(STAMP)
	$(PY) -m pytest

bench: $(STAMP)
	$(PY) benchmarks/centroids.py

clean-venv:
	rm -rf $(VENV)

# The demo plus its fusion model trained with the VoD recipe's augmentation at the same budget
# (docs/training.md); the first two models are the same as `make demo`'s.
.PHONY: demo-augmentation
demo-augmentation: $(STAMP)
	$(PY) examples/train_demo.py --augmentation compare --out outputs/demo_augmentation
