"""OpenPCDet's real code for the integration tests: the ``openpcdet`` fixture.

OpenPCDet is not on the package registry; ``<repo>/../shared/thirdparty/openpcdet-8caccce.tar.gz``
(its commit 8caccce, unmodified) is unpacked once per session into a temporary folder. ``setup.py``
would compile seven CUDA extension modules and write ``pcdet/version.py``; without CUDA the fixture
writes ``version.py`` as ``setup.py`` does and replaces only those seven modules with stand-ins that
raise when used. Everything else runs as released. The archive is absent in a user's clone without
``../shared``: the tests skip there, and FAIL under ``CI=true``.
"""

from __future__ import annotations

import importlib
import os
import sys
import tarfile
import types
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
ARCHIVE = REPO_ROOT.parent / "shared" / "thirdparty" / "openpcdet-8caccce.tar.gz"
PREFIX = "OpenPCDet-8caccce"
#: the compiled modules of OpenPCDet's setup.py: (package folder, module name)
EXTENSIONS = (
    ("pcdet/ops/iou3d_nms", "iou3d_nms_cuda"),
    ("pcdet/ops/roiaware_pool3d", "roiaware_pool3d_cuda"),
    ("pcdet/ops/roipoint_pool3d", "roipoint_pool3d_cuda"),
    ("pcdet/ops/pointnet2/pointnet2_stack", "pointnet2_stack_cuda"),
    ("pcdet/ops/pointnet2/pointnet2_batch", "pointnet2_batch_cuda"),
    ("pcdet/ops/bev_pool", "bev_pool_ext"),
    ("pcdet/ops/ingroup_inds", "ingroup_inds_cuda"),
)
#: pure-Python packages OpenPCDet imports at module level (installed by `make test`)
REQUIRED = ("easydict", "yaml", "skimage", "scipy", "numba", "SharedArray", "pyquaternion", "tensorboardX",
            "cv2", "kornia", "av2", "spconv")

STAND_IN = '''"""Stand-in for OpenPCDet's compiled extension {name} (not built: no CUDA on this machine)."""


def __getattr__(attr):
    if attr.startswith("__"):
        raise AttributeError(attr)
    raise RuntimeError("{name}.%s: OpenPCDet's compiled extension is not built here (test stand-in)" % attr)
'''


def _missing(reason: str) -> None:
    if os.environ.get("CI") == "true":
        pytest.fail(f"CI=true: {reason}")
    pytest.skip(reason)


def _stub_torchvision() -> None:
    """OpenPCDet's data_processor imports torchvision at module level; the registry's wheels are CUDA
    builds that do not load with the CPU torch. A stand-in module whose attributes raise when used."""
    try:
        importlib.import_module("torchvision")
        return
    except Exception:  # noqa: BLE001 - absent, or a build that does not load
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]

    class _Raising(types.ModuleType):
        def __getattr__(self, attr):
            if attr.startswith("__"):
                raise AttributeError(attr)
            raise RuntimeError(f"{self.__name__}.{attr}: torchvision stand-in (not installed here)")

    tv = _Raising("torchvision")
    # mmengine's Runner records the environment (collect_env reads torchvision.__version__ when the import works):
    # without a version, every mmdet3d runner test after an OpenPCDet one in the same session would fail
    tv.__version__ = "0.0.0+stand-in"
    tv.transforms = _Raising("torchvision.transforms")
    sys.modules["torchvision"] = tv
    sys.modules["torchvision.transforms"] = tv.transforms


def unpack_openpcdet(dest: Path) -> Path:
    """Unpack the archive into ``dest``; version.py and the seven stand-ins written. Returns the root."""
    with tarfile.open(ARCHIVE) as tar:
        tar.extractall(dest, filter="data")
    root = dest / PREFIX
    (root / "pcdet" / "version.py").write_text('__version__ = "0.6.0+8caccce"\n')
    for folder, name in EXTENSIONS:
        (root / folder / f"{name}.py").write_text(STAND_IN.format(name=name))
    return root


@pytest.fixture(scope="session")
def openpcdet(tmp_path_factory) -> Path:
    """Root of an unpacked OpenPCDet (``pcdet/``, ``tools/``), importable as ``pcdet``."""
    if not ARCHIVE.is_file():
        _missing(f"OpenPCDet archive not found at {ARCHIVE} (it is beside the repository in ../shared)")
    for name in REQUIRED:
        try:
            importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001
            _missing(f"OpenPCDet needs {name!r} ({exc}); `make test` installs it")
    _stub_torchvision()
    root = unpack_openpcdet(tmp_path_factory.mktemp("openpcdet"))
    sys.path.insert(0, str(root))
    sys.path.insert(0, str(root / "tools"))
    yield root
    sys.path.remove(str(root))
    sys.path.remove(str(root / "tools"))


@pytest.fixture
def openpcdet_copy(openpcdet, tmp_path) -> Path:
    """A second, private unpacked copy (for tests that edit OpenPCDet's files); not on sys.path."""
    return unpack_openpcdet(tmp_path / "copy")
