"""Every integration module imports without OpenPCDet, mmdet3d, mmengine or spconv (and imports none of them)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[2] / "src"
CODE = """
import sys
for name in ("spconv", "mmdet3d", "mmengine", "mmcv", "mmdet", "pcdet"):
    sys.modules[name] = None  # any import of them raises ImportError
import mssf_blocks.integrations.openpcdet, mssf_blocks.integrations.mmdet3d
import mssf_blocks.integrations.openpcdet_backbones, mssf_blocks.integrations.mmdet3d_plugin as plugin
assert plugin.REGISTERED is False
loaded = [m for m in ("spconv", "mmdet3d", "mmengine", "mmcv", "mmdet", "pcdet") if sys.modules.get(m) is not None]
assert not loaded, loaded
print("ok")
"""


def test_integrations_import_without_the_frameworks():
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True, timeout=120,
                         env={"PYTHONPATH": str(SRC), "OMP_NUM_THREADS": "1"})
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
