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
	# test-only (tests/integrations): the real mmdetection3d 1.4.0 with mmcv 2.1.0's compiled CPU ops
	# (../shared/wheels, README there says how it was built; without it the mmcv-lite fallback keeps the
	# registry tests running and the training tests skip). --no-deps because the wheels' own requirements
	# pull opencv-python with GUI libraries, open3d and numpy < 2; what import, train and val need follows.
	$(PY) -m pip install --quiet --no-deps mmengine==0.10.7 mmdet3d==1.4.0 mmdet==3.3.0 nuscenes-devkit lyft_dataset_sdk
	$(PY) -m pip install --quiet --no-deps $(firstword $(wildcard ../shared/wheels/mmcv-2.1.0-*.whl) mmcv-lite==2.1.0)
	$(PY) -m pip install --quiet addict yapf termcolor rich opencv-python-headless
	# test-only (tests/integrations): what OpenPCDet (../shared/thirdparty, unpacked by the tests) imports at
	# module level; av2 and kornia --no-deps (their own requirements pull CUDA builds and are not imported).
	$(PY) -m pip install --quiet scipy scikit-image easydict pyyaml SharedArray pyquaternion tensorboardX numba pandas pyarrow universal_pathlib
	$(PY) -m pip install --quiet --no-deps av2==0.3.6 kornia==0.6.8
	# test-only (tests/integrations): what mmdet3d's models, datasets and evaluation import at module level
	$(PY) -m pip install --quiet scipy shapely terminaltables pycocotools tqdm matplotlib six pyquaternion \
	    networkx plyfile scikit-image trimesh pandas scikit-learn cachetools numba pyyaml
	touch $(STAMP)

demo: $(STAMP)
	$(PY) examples/train_demo.py

quickstart: $(STAMP)
	$(PY) examples/quickstart.py

# The docs site (mkdocs.yml) is built with --strict after the tests: a broken link fails `make test`.
DOCS_STAMP := $(VENV)/.mssf-docs-installed
$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e ".[docs]"
	touch $(DOCS_STAMP)

test: $(STAMP) $(DOCS_STAMP)
	$(PY) -m pytest
	$(PY) -m mkdocs build --strict --site-dir $(VENV)/site  # not --quiet: it hides the warnings --strict counts

# One target per benchmark script: `make bench-centroids`, `make bench-msdff`, `make bench-detectors`,
# `make bench-threads`, ... (any benchmarks/NAME.py, options in BENCH_ARGS); `make bench` runs them all.
# Durations: docs/performance.md ("Benchmark targets"). Not gpu_check.py: a device check (`make gpu-check`), nor
# gpu_bundle.py, which prepares its bundle (`make gpu-bundle`).
BENCHMARKS := $(patsubst benchmarks/%.py,%,$(filter-out benchmarks/_% benchmarks/gpu_check.py benchmarks/gpu_bundle.py,$(wildcard benchmarks/*.py)))
BENCH_ARGS ?=

bench: $(addprefix bench-,$(BENCHMARKS))

# (a pattern rule, not .PHONY: make skips implicit rules for phony targets)
bench-%: benchmarks/%.py $(STAMP)
	$(PY) $< $(BENCH_ARGS)

clean-venv:
	rm -rf $(VENV)

# The demo plus its fusion model trained with the VoD recipe's augmentation at the same budget
# (docs/training.md); the first two models are the same as `make demo`'s.
.PHONY: demo-augmentation
demo-augmentation: $(STAMP)
	$(PY) examples/train_demo.py --augmentation compare --out outputs/demo_augmentation

# The device check on a GPU machine with network (tests on CUDA, the sampling op, MSDFF, each detector;
# docs/gpus.md). It installs what it needs into the environment it runs in (spconv for the GPU's CUDA version).
# A bare GPU machine without network runs gpu_check.py --bundle instead (docs/gpus.md, "The device check").
.PHONY: gpu-check
gpu-check: $(STAMP)
	$(PY) benchmarks/gpu_check.py --out outputs/gpu_check

# What that bare machine needs and lacks (spconv, its dependencies, mmcv's source archive), into the folder a
# device call carries (.carry/gpu_bundle, ignored by git); downloads once into ~/.cache/mssf-blocks/gpu_bundle.
# Only python3 and pip are needed (no venv).
.PHONY: gpu-bundle
gpu-bundle:
	$(PYTHON) benchmarks/gpu_bundle.py --out .carry/gpu_bundle

# The declared floors, tested (docs/compatibility.md): the core and integration tests on the floor torch
# (2.1.2) and the newest torch on the registry, the core blocks on every declared Python; counts per
# environment. Environments in ~/.cache/mssf-blocks/compat-envs (about 19 GB), reused while unchanged. .ci/run runs it.
.PHONY: test-compat
test-compat:
	bash .ci/compat_envs.sh
