"""``python -m mssf_examples.openpcdet --cpu ...``: OpenPCDet's tools on a machine without CUDA (a laptop, CI).

OpenPCDet's ``setup.py develop`` compiles seven CUDA extension modules and writes ``pcdet/version.py``; without
CUDA it fails, so ``pcdet`` is used from its clone instead. :func:`prepare_cpu` then, before ``pcdet`` is
imported, and only for what is missing:

* puts the clone's root (the parent of ``tools/``) on ``sys.path`` when ``pcdet`` is not importable;
* provides ``pcdet.version`` when ``version.py`` was never written;
* provides each compiled extension module that was not built as a stand-in that raises when used (the
  detectors here never call them: rotated NMS / IoU are replaced by the project's pure-torch ones);
* provides ``torchvision`` as a stand-in when it does not import (the registry's wheels are CUDA builds;
  ``pcdet.datasets`` imports it at module level, the VoD configs never use it);
* makes ``Tensor.cuda()`` (``load_data_to_gpu``, ``model.cuda()``, the heads) return the tensor unchanged when
  torch has no CUDA.

``av2`` and ``kornia`` (imported by ``pcdet.datasets`` at module level) must be installed
(``pip install --no-deps av2==0.3.6 kornia==0.6.8``): without them the error says so.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
import types
from pathlib import Path
from typing import List

from mssf_blocks.errors import MSSFError

__all__ = ["prepare_cpu", "EXTENSIONS"]

#: OpenPCDet's compiled modules (its setup.py): package folder under pcdet/, module name
EXTENSIONS = (
    ("ops/iou3d_nms", "iou3d_nms_cuda"),
    ("ops/roiaware_pool3d", "roiaware_pool3d_cuda"),
    ("ops/roipoint_pool3d", "roipoint_pool3d_cuda"),
    ("ops/pointnet2/pointnet2_stack", "pointnet2_stack_cuda"),
    ("ops/pointnet2/pointnet2_batch", "pointnet2_batch_cuda"),
    ("ops/bev_pool", "bev_pool_ext"),
    ("ops/ingroup_inds", "ingroup_inds_cuda"),
)


class _StandIn(types.ModuleType):
    """A module whose every attribute raises when looked up (what is missing says what it is)."""

    def __init__(self, name: str, why: str) -> None:
        super().__init__(name)
        self.__doc__ = f"stand-in for {name}: {why}"
        self._why = why

    def __getattr__(self, attr):
        if attr.startswith("__"):
            raise AttributeError(attr)
        raise RuntimeError(f"{self.__name__}.{attr}: {self._why} (python -m mssf_examples.openpcdet --cpu)")


def _pcdet_dir(tools_dir: Path) -> Path:
    spec = importlib.util.find_spec("pcdet")
    if spec is None:
        root = Path(tools_dir).resolve().parent
        if not (root / "pcdet" / "__init__.py").is_file():
            raise MSSFError(f"--cpu: pcdet is not importable and {root} (the parent of the script's folder) has no "
                            "pcdet/: run OpenPCDet's tools/ scripts from its clone")
        sys.path.insert(0, str(root))
        spec = importlib.util.find_spec("pcdet")
    return Path(list(spec.submodule_search_locations)[0])


def prepare_cpu(tools_dir) -> List[str]:
    """Make ``pcdet`` importable and runnable without CUDA (module docstring); returns what was stood in."""
    import torch

    done: List[str] = []
    pcdet = _pcdet_dir(Path(tools_dir))
    if not (pcdet / "version.py").is_file() and "pcdet.version" not in sys.modules:
        version = types.ModuleType("pcdet.version")
        version.__version__ = "0.0.0+unbuilt"  # what setup.py would write, without its git hash
        sys.modules["pcdet.version"] = version
        done.append("pcdet.version")
    for folder, name in EXTENSIONS:
        full = "pcdet." + folder.replace("/", ".") + "." + name
        built = [p for p in (pcdet / folder).glob(f"{name}*") if p.suffix in (".so", ".pyd", ".py")]
        if not built and full not in sys.modules:
            sys.modules[full] = _StandIn(full, "OpenPCDet's compiled CUDA extension is not built here")
            done.append(full)
    try:
        importlib.import_module("torchvision")
    except Exception:  # noqa: BLE001 - absent, or a CUDA build that does not load with this torch
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        tv = _StandIn("torchvision", "torchvision does not import here")
        tv.__version__ = "0.0.0+stand-in"  # read by environment reports (mmengine's collect_env) in this process
        tv.transforms = _StandIn("torchvision.transforms", "torchvision does not import here")
        sys.modules.update({"torchvision": tv, "torchvision.transforms": tv.transforms})
        done.append("torchvision")
    for name in ("av2", "kornia"):
        try:
            importlib.import_module(name)
        except ImportError as exc:
            raise MSSFError(f"--cpu: pcdet.datasets imports {name} at module level and it does not import ({exc}); "
                            "pip install --no-deps av2==0.3.6 kornia==0.6.8 (their own dependencies are not needed "
                            "by the VoD configs)") from exc
    if not torch.cuda.is_available():
        torch.Tensor.cuda = _cuda_identity  # model.cuda() goes through it too
        done.append("Tensor.cuda")
    return done


def _cuda_identity(self, *args, **kwargs):
    """``Tensor.cuda`` on a machine without CUDA (``--cpu``): the tensor, where it is."""
    return self
