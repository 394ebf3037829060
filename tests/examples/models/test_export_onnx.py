"""examples/export_onnx.py: the pure-torch MSSF-PointPillars (MSDFF fusion, QueryInit, pillar lifts, the
semantic-guided head, the anchor head) exported to ONNX and run in onnxruntime on three generated scenes
with different point / pillar / voxel counts, against the eager PyTorch detector (its default CPU plans)."""

import re
import runpy
import sys
from pathlib import Path

import pytest

pytest.importorskip("spconv.pytorch")  # (the example detectors' module imports it; PointPillars does not use it)
pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")

SCRIPT = Path(__file__).resolve().parents[3] / "examples" / "export_onnx.py"


def test_export_onnx_example_matches_pytorch(capsys, monkeypatch, tmp_path, one_thread):
    out_path = tmp_path / "pp.onnx"
    # one fusion block keeps it short (the script's default is two)
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), "--out", str(out_path), "--blocks", "1", "--fusion", "msdff"])
    with pytest.raises(SystemExit) as exc:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    out = capsys.readouterr().out
    assert exc.value.code == 0, out
    assert out_path.is_file()
    rows = re.findall(r"points (\d+), pillars (\d+), lift voxels \[(\d+)\]: max \|onnxruntime - torch\| = (\S+)", out)
    assert len(rows) == 3
    assert len({r[2] for r in rows}) == 3  # three different voxel counts through one graph
    assert max(float(r[3]) for r in rows) <= 1e-4
