"""The quick-start example (README's main job until the training demo) runs and reports consistent counts."""

import re
import runpy
import sys
from pathlib import Path

import pytest

pytest.importorskip("spconv.pytorch")

SCRIPT = Path(__file__).resolve().parents[3] / "examples" / "quickstart.py"


@pytest.mark.parametrize("fusion", ["msdff", "sff"])
def test_quickstart_runs(fusion, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), "--fusion", fusion])
    with pytest.raises(SystemExit) as exc:
        runpy.run_path(str(SCRIPT), run_name="__main__")
    assert exc.value.code == 0
    out = capsys.readouterr().out
    stage1 = re.search(r"stage 1 \((\w+)\): (\d+) voxels at stride \(2, 2, 2\), (\d+) hold radar points.*, (\d+) project into", out)
    assert stage1 and stage1.group(1) == fusion.upper()
    n1, with_points, projected = (int(stage1.group(i)) for i in (2, 3, 4))
    assert 0 < with_points <= n1 and 0 < projected <= n1
    zeros = int(re.search(r"voxels outside the image get exactly 0: (\d+)", out).group(1))
    assert zeros == n1 - projected  # every voxel outside the image, and only those, gets a zero image feature
    head = re.search(r"semantic head: (\d+) foreground / (\d+) ignored / (\d+) background", out)
    n2 = int(re.search(r"stage 2 \(SFF\): (\d+) voxels", out).group(1))
    assert sum(int(head.group(i)) for i in (1, 2, 3)) == n2
    assert int(head.group(1)) > 0
