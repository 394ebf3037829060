"""Every OpenPCDet model config of the project, shrunk for the CPU by the test module of its detector kind.

``shrink(name, ckpt, folder)`` picks the ``small`` of test_openpcdet_pointpillar.py (MSSF-PP and its twin),
test_openpcdet_voxelnext2d.py (VoxelNeXt-2D) or test_openpcdet_vod.py (the voxel models: SECOND, VoxelNeXt,
CenterPoint), so a test that runs many kinds (TJ4D, single-scan VoD) shrinks each as its own tests do. Not a
test module: imported by them (their folder is on ``sys.path``).
"""

from __future__ import annotations

import test_openpcdet_pointpillar as pointpillar
import test_openpcdet_vod as vod
import test_openpcdet_voxelnext2d as voxelnext2d

#: the pillar configs (the rest are voxel configs), and each MSSF config's radar-only twin
PILLARS = ("mssf_pointpillar", "pointpillar_radar", "mssf_voxelnext2d", "voxelnext2d_radar")
TWINS = {"mssf_second": "second_radar", "mssf_voxelnext": "voxelnext_radar", "mssf_centerpoint": "centerpoint_radar",
         "mssf_pointpillar": "pointpillar_radar", "mssf_voxelnext2d": "voxelnext2d_radar"}


def shrink(name, ckpt, folder="vod_models"):
    """``cfgs/<folder>/<name>.yaml`` shrunk for the CPU (``name`` may carry a suffix, e.g. ``_single_scan``)."""
    if "pointpillar" in name:
        return pointpillar.small(name, ckpt, folder)
    if "voxelnext2d" in name:
        return voxelnext2d.small(name, ckpt, folder)
    return vod.small(name, ckpt, folder)
