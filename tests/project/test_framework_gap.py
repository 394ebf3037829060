"""benchmarks/framework_gap.py (issue 44's evidence inside the frameworks): its pieces on hand-worked inputs, and
the whole mmdetection3d half in its smoke size (the real Runner, the real VoD metric)."""

import json
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "examples"))

from _gap_mmdet3d import _retarget  # noqa: E402
from _gap_openpcdet import parse_vod_log  # noqa: E402

# the lines VoDDataset.evaluation writes (examples/mssf_examples/openpcdet/vod_dataset.py), after OpenPCDet's
# logger prefix, twice: the parser must take the last tables
_TABLE = """2026-12-04 22:52:45,404   INFO  VoD entire_area:
  Car         AP3D R40  {c:6.2f}  APBEV R40  50.00  AP3D R11  {c11:6.2f}  (GT 4, detections 9)
  Pedestrian  AP3D R40  20.00  APBEV R40  21.00  AP3D R11  22.00  (GT 8, detections 200)
  Cyclist     AP3D R40  30.00  APBEV R40  31.00  AP3D R11  32.00  (GT 6, detections 0)
  mAP3D R40  {m:6.2f}
VoD driving_corridor:
  Car         AP3D R40   1.00  APBEV R40   2.00  AP3D R11   3.00  (GT 2, detections 1)
  Pedestrian  AP3D R40   4.00  APBEV R40   5.00  AP3D R11   6.00  (GT 3, detections 4)
  Cyclist     AP3D R40   7.00  APBEV R40   8.00  AP3D R11   9.00  (GT 1, detections 0)
  mAP3D R40   4.00
"""


def test_parse_vod_log_takes_the_last_tables():
    text = "start\n" + _TABLE.format(c=99.0, c11=98.0, m=49.67) + "epoch 2\n" + _TABLE.format(c=10.0, c11=12.0, m=20.0)
    m = parse_vod_log(text)
    assert m["VoD/entire_area/Car/AP3D_R40"] == 10.0 and m["VoD/entire_area/Car/AP3D_R11"] == 12.0
    assert m["VoD/entire_area/mAP/AP3D_R40"] == pytest.approx(20.0)  # (10 + 20 + 30) / 3, the log's own mAP
    assert m["VoD/entire_area/mAP/AP3D_R11"] == pytest.approx((12 + 22 + 32) / 3)
    assert m["VoD/driving_corridor/mAP/AP3D_R11"] == pytest.approx(6.0)
    assert m["VoD/driving_corridor/Cyclist/APBEV_R40"] == 8.0
    assert parse_vod_log("no tables") == {}


def test_retarget_moves_the_xy_extent_and_keeps_anchor_heights():
    old, new = [0, -25.6, -3, 51.2, 25.6, 2], (0.0, -12.8, -3.0, 25.6, 12.8, 2.0)
    cfg = {"range": list(old), "anchors": [[0, -25.6, -1.78, 51.2, 25.6, -1.78], [0, -25.6, -0.6, 51.2, 25.6, -0.6]],
           "other": [1, 2, 3, 4, 5, 6], "nested": {"r": tuple(old)}}
    _retarget(cfg, old, new)
    assert cfg["range"] == list(new) and cfg["nested"]["r"] == new
    assert cfg["anchors"] == [[0, -12.8, -1.78, 25.6, 12.8, -1.78], [0, -12.8, -0.6, 25.6, 12.8, -0.6]]
    assert cfg["other"] == [1, 2, 3, 4, 5, 6]


def test_mmdet3d_half_runs_in_its_smoke_size(tmp_path):
    sys.path.insert(0, str(ROOT / "tests" / "integrations"))
    from mmdet3d_vod_tree import require_mmdet3d  # skips without mmdet3d, fails under CI=true

    require_mmdet3d()
    import framework_gap

    threads = torch.get_num_threads()
    try:
        assert framework_gap.main(["--smoke", "--frameworks", "mmdet3d", "--out", str(tmp_path)]) == 0
    finally:
        torch.set_num_threads(threads)
    report = json.loads((tmp_path / "metrics.json").read_text())
    models = report["results"]["mmdet3d"]
    assert list(models) == ["MSSF-PP", "PointPillars (radar only)"]
    for r in models.values():
        assert {"VoD/entire_area/mAP/AP3D_R11", "VoD/driving_corridor/mAP/AP3D_R40"} <= set(r["metrics"])
    assert "mmdet3d" in report["gap_AP3D_R11_entire_area"]
    # the tree a framework reads holds the VoD camera's full resolution (the kit's 40 px rule as on VoD)
    from PIL import Image

    with Image.open(next((tmp_path / "view_of_delft" / "radar_5frames" / "training" / "image_2").glob("*.jpg"))) as im:
        assert im.size == (1936, 1216)
