"""Shared test set-up.

* Puts ``examples/`` on ``sys.path`` so tests can import the ``mssf_examples`` package, and
  ``tests/helpers`` and ``tests/references`` so every test folder imports the shared modules by name.
* ``realdata_root`` fixture: the folder of real sensor frames (``<repo>/../shared/realdata``, or the
  ``MSSF_REALDATA`` environment variable). The data's licences forbid shipping it, so tests that need it
  skip with a message when it is absent.
"""

import os
import sys
from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parent.parent
_EXAMPLES = str(REPO_ROOT / "examples")
if _EXAMPLES not in sys.path:
    sys.path.insert(0, _EXAMPLES)
# The shared helpers (tests/helpers: doc readers, the mistakes registry and its cases, the block tester)
# and the independent references (tests/references) are imported by module name from every test folder
# (``from fusion_references import ...``): one name per module, so the mistakes registry is one object.
for _shared in ("helpers", "references"):
    _path = str(REPO_ROOT / "tests" / _shared)
    if _path not in sys.path:
        sys.path.insert(0, _path)

from mssf_examples.training.threads import DEFAULT_THREADS  # noqa: E402

# The suite's thread count (one place for it: mssf_examples/training/threads.py, which says why); an explicit
# OMP_NUM_THREADS wins.
if "OMP_NUM_THREADS" not in os.environ:
    torch.set_num_threads(DEFAULT_THREADS)

#: Default location of the real frames (never copied into the repository).
DEFAULT_REALDATA = REPO_ROOT.parent / "shared" / "realdata"


def realdata_path() -> Path:
    """``$MSSF_REALDATA`` when set, else ``<repo>/../shared/realdata``."""
    env = os.environ.get("MSSF_REALDATA")
    return Path(env).expanduser() if env else DEFAULT_REALDATA


@pytest.fixture(scope="session")
def realdata_root() -> Path:
    """Root of the real frames (``vod/``, ``kitti/``); skips the test when it does not exist."""
    root = realdata_path()
    if not root.is_dir():
        pytest.skip(
            f"real sensor frames not found at {root} (set MSSF_REALDATA or place them at "
            f"{DEFAULT_REALDATA}); they are licence-restricted and not part of the repository"
        )
    return root


@pytest.fixture
def one_thread():
    """Run the test with one intra-op thread and restore the previous count afterwards.

    Test modules opt in with ``pytestmark = pytest.mark.usefixtures("one_thread")`` and say why
    (tiny tensors where OpenMP spinning dominates on a loaded machine; spconv's threaded CPU kernels
    are not bit-deterministic in float32 and wrong in float64: tests/checks/test_spconv_inputs.py).
    """
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


#: The devices the device-parametrised tests run on: the CPU, plus CUDA when this torch build sees a GPU.
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """``torch.device`` to run the test on: once per entry of :data:`DEVICES` (``cpu``; ``cuda`` where
    available), so a GPU machine runs the same assertions (``benchmarks/gpu_check.py``)."""
    return torch.device(request.param)


@pytest.fixture(autouse=True)
def _spconv_state_dict_loading_as_installed():
    """Put spconv's own state-dict loading back after each test.

    Importing ``mmdet3d.models`` (the mmdet3d integration tests) replaces
    ``spconv.pytorch.modules.SparseModule._load_from_state_dict`` and sets ``SparseModule._version = 2``
    for the whole process: mmdet3d's conversion of spconv-1 checkpoints, which permutes the conv
    weights of any state dict that lacks spconv's version metadata. The tests after them load our own
    state dicts (the authors' stages, checkpoints) as a process without mmdet3d does; a user's process
    that imports mmdet3d gets mmdet3d's behaviour (docs/frameworks.md, "Known limits").
    """
    yield
    modules = sys.modules.get("spconv.pytorch.modules")
    if modules is None:
        return
    patched = modules.SparseModule.__dict__.get("_load_from_state_dict")
    if patched is not None and getattr(patched, "__module__", "").startswith("mmdet3d"):
        del modules.SparseModule._load_from_state_dict  # spconv 2.3 defines neither: nn.Module's again
        if "_version" in modules.SparseModule.__dict__:
            del modules.SparseModule._version
