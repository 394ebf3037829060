"""Every OpenPCDet model config of the project, shrunk for the CPU by the test module of its detector kind, and
the one import of ``test_openpcdet_vod.py``'s fixture and loops for the pillar kinds' test modules.

``shrink(name, ckpt, folder)`` picks the ``small`` of test_openpcdet_pointpillar.py (MSSF-PP and its twin),
test_openpcdet_voxelnext2d.py (VoxelNeXt-2D) or test_openpcdet_vod.py (the voxel models: SECOND, VoxelNeXt,
CenterPoint), so a test that runs many kinds (TJ4D, single-scan VoD) shrinks each as its own tests do.
``build``, ``load``, ``overfit``, ``train`` and the ``tools`` fixture (the generated VoD tree) are
``test_openpcdet_vod``'s, re-exported for test_openpcdet_pointpillar.py and test_openpcdet_voxelnext2d.py: a test
module that imports ``tools`` into its namespace is where pytest finds the fixture (module scope: each such
module gets its own tree, ~2-6 s). Not a test module: imported by them (their folder is on ``sys.path``); the
kinds' modules are imported when ``shrink`` needs them, since they import this one.
"""

from __future__ import annotations

import test_openpcdet_vod as vod
from test_openpcdet_vod import build, load, overfit, tools, train

__all__ = ["PILLARS", "TWINS", "shrink", "build", "load", "overfit", "tools", "train"]

#: the pillar configs (the rest are voxel configs), and each MSSF config's radar-only twin
PILLARS = ("mssf_pointpillar", "pointpillar_radar", "mssf_voxelnext2d", "voxelnext2d_radar")
TWINS = {"mssf_second": "second_radar", "mssf_voxelnext": "voxelnext_radar", "mssf_centerpoint": "centerpoint_radar",
         "mssf_pointpillar": "pointpillar_radar", "mssf_voxelnext2d": "voxelnext2d_radar"}


def shrink(name, ckpt, folder="vod_models"):
    """``cfgs/<folder>/<name>.yaml`` shrunk for the CPU (``name`` may carry a suffix, e.g. ``_single_scan``)."""
    if "pointpillar" in name:
        import test_openpcdet_pointpillar as pointpillar

        return pointpillar.small(name, ckpt, folder)
    if "voxelnext2d" in name:
        import test_openpcdet_voxelnext2d as voxelnext2d

        return voxelnext2d.small(name, ckpt, folder)
    return vod.small(name, ckpt, folder)
