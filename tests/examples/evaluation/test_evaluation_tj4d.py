"""Hand-worked cases for ``protocol="tj4d"`` (the MSSF authors' TJ4DRadSet evaluation), one per rule."""

from __future__ import annotations

import pytest
import torch

from mssf_examples.evaluation.metrics import TJ4D_IOU_THRESHOLDS, TJ4D_LOOSE_IOU_THRESHOLDS, TJ4D_STRICT_IOU_THRESHOLDS, evaluate
from mssf_examples.evaluation.kitti import _from_kitti
from mssf_examples.evaluation.tj4d import tj4d_difficulty
from mssf_examples.data.kitti_io import KittiObjects

F64 = dict(dtype=torch.float64)
CLASSES = ["Car", "Pedestrian", "Cyclist", "Truck"]
TALL = (100.0, 100.0, 200.0, 200.0)
CAR = (1.5, 2.0, 4.0)


def objects(rows, scores=None):
    """``rows``: ``(type, 2D box, (h, w, l), (x, y, z), ry, occlusion, truncation)`` (last two optional)."""
    g = len(rows)
    return KittiObjects(
        names=[r[0] for r in rows],
        truncation=torch.tensor([r[6] if len(r) > 6 else 0.0 for r in rows], **F64),
        occlusion=torch.tensor([r[5] if len(r) > 5 else 0 for r in rows], dtype=torch.long),
        alpha=torch.zeros(g, **F64), boxes_2d=torch.tensor([r[1] for r in rows], **F64).reshape(g, 4),
        dimensions=torch.tensor([r[2] for r in rows], **F64).reshape(g, 3),
        location=torch.tensor([r[3] for r in rows], **F64).reshape(g, 3),
        rotation_y=torch.tensor([r[4] for r in rows], **F64).reshape(g),
        score=None if scores is None else torch.tensor(scores, **F64))


def car(z=10.0, x=0.0, name="Car", box=TALL, occ=0, trunc=0.0):
    return (name, box, CAR, (x, 0.0, z), 0.0, occ, trunc)


def test_difficulty_range_bins_and_kitti_hard_limits():
    # r = |location|: (0, 50] -> 0, (50, 70] -> 1, else 2 (r = 0 too); -1 for occlusion > 2,
    # truncation > 0.5 or an image box at most 25 px high.
    rows = [car(z=49.9), car(z=50.0), car(z=30.0, x=40.0), car(z=70.0), car(z=70.01), car(z=0.0),
            car(occ=3), car(trunc=0.51), car(box=(0, 100, 10, 125)), car(box=(0, 100, 10, 125.5)), car(occ=2, trunc=0.5)]
    diff = tj4d_difficulty(_from_kitti(objects(rows)))
    assert diff.tolist() == [0, 0, 0, 1, 2, 2, -1, -1, -1, 0, 0]  # (30, 40) is 50 m away: bin 0


def test_range_bins_are_cumulative_and_detections_never_ignored():
    # GTs at 30, 60 and 80 m, each detected exactly (scores 0.9, 0.8, 0.7), plus a false positive at
    # 60 m (0.6) with no GT. range_0_50: the 60 and 80 m GTs are ignored, their detections neutral;
    # the 60 m false positive still counts (detections are never ignored).
    gts = [objects([car(30.0), car(60.0), car(80.0)])]
    dets = [objects([car(30.0), car(60.0), car(80.0), car(60.0, x=10.0)], [0.9, 0.8, 0.7, 0.6])]
    res = evaluate(dets, gts, ["Car"], protocol="tj4d")
    assert [res[r]["Car"]["num_gt"] for r in ("range_0_50", "range_0_70", "range_all")] == [1, 2, 3]
    # range_0_50: one TP (0.9) -> thresholds [0.9]; at 0.9 precision 1/1 -> slot 0 = 1: the authors'
    # "R40" sums all 41 slots / 40 = 2.5; R11 = 100/11. (The false positive scores below the threshold.)
    assert res["range_0_50"]["Car"]["AP3D_R40"] == pytest.approx(2.5)
    assert res["range_0_50"]["Car"]["AP3D_R11"] == pytest.approx(100 / 11)
    # range_all: 3 TPs, 3 GTs; get_thresholds keeps 0.9, 0.8, 0.7 (each recall 1/3 step is >= 1/40):
    # slots 0..2 precision 1 -> R40 = 3/40 = 7.5.
    assert res["range_all"]["Car"]["AP3D_R40"] == pytest.approx(7.5)


def test_perfect_detector_scores_100_in_r40_with_slot_zero():
    # 40 GTs detected exactly: 40 thresholds, slots 0..39 = 1, slot 40 = 0. VoD kit R40 (slots 1..40)
    # = 39/40 = 97.5; the authors' TJ4D AP (slots 0..40 / 40) = 40/40 = 100.
    gts = [objects([car(10.0)]) for _ in range(40)]
    dets = [objects([car(10.0)], [1.0 - 0.01 * i]) for i in range(40)]
    tj = evaluate(dets, gts, ["Car"], protocol="tj4d")["range_all"]["Car"]["AP3D_R40"]
    vod = evaluate(dets, gts, ["Car"], protocol="vod")["entire_area"]["Car"]["AP3D_R40"]
    assert (tj, vod) == pytest.approx((100.0, 97.5))


def test_iou_sets():
    # A car detection shifted 1.5 m along its 4 m length: BEV IoU 2.5 / 5.5 = 0.4545 (3D alike).
    # Strict set (0.5): a miss -> no TP, AP 0; loose set (0.25) and the headline set for Pedestrian-like
    # classes match it. The headline set takes Car at 0.5.
    assert set(TJ4D_STRICT_IOU_THRESHOLDS.values()) == {0.5} and set(TJ4D_LOOSE_IOU_THRESHOLDS.values()) == {0.25}
    assert TJ4D_IOU_THRESHOLDS == {"Car": 0.5, "Pedestrian": 0.25, "Cyclist": 0.25, "Truck": 0.5}
    gts = [objects([car(10.0)])]
    dets = [objects([("Car", TALL, CAR, (1.5, 0.0, 10.0), 0.0)], [0.9])]
    strict = evaluate(dets, gts, ["Car"], TJ4D_STRICT_IOU_THRESHOLDS, protocol="tj4d")
    loose = evaluate(dets, gts, ["Car"], TJ4D_LOOSE_IOU_THRESHOLDS, protocol="tj4d")
    assert strict["range_all"]["Car"]["APBEV_R40"] == 0.0
    assert loose["range_all"]["Car"]["APBEV_R40"] == pytest.approx(2.5)


def test_no_neighbouring_classes_and_no_40px_rule():
    # A Van GT under a Car detection: VoD ignores the Van for Car (neutral), TJ4D does not know Vans (the
    # detection is a false positive). A 30 px high car counts in TJ4D (> 25 px), not in VoD (<= 40 px).
    van = ("Van", TALL, CAR, (0.0, 0.0, 10.0), 0.0)
    small = car(20.0, box=(100, 100, 200, 130))
    gts = [objects([van, small])]
    dets = [objects([car(10.0), car(20.0, box=(100, 100, 200, 130))], [0.9, 0.8])]
    tj = evaluate(dets, gts, ["Car"], protocol="tj4d")["range_all"]["Car"]
    vod = evaluate(dets, gts, ["Car"], protocol="vod")["entire_area"]["Car"]
    assert tj["num_gt"] == 1 and vod["num_gt"] == 0
    # TJ4D: thresholds [0.8] (the small car's TP); at 0.8 the van's detection is an FP: precision 1/2.
    assert tj["AP3D_R40"] == pytest.approx(0.5 / 40 * 100)
    assert all(v != v for k, v in vod.items() if k.startswith("AP"))  # no counted GT: NaN


def test_truck_class_and_mean():
    # Truck is evaluated like the others; mAP averages the classes with a counted GT.
    truck = ("Truck", TALL, (3.0, 2.5, 8.0), (0.0, 0.0, 20.0), 0.0)
    gts = [objects([car(10.0), truck])]
    dets = [objects([car(10.0), truck], [0.9, 0.8])]
    res = evaluate(dets, gts, CLASSES, protocol="tj4d")["range_all"]
    assert res["Truck"]["AP3D_R40"] == pytest.approx(2.5) and res["Car"]["AP3D_R40"] == pytest.approx(2.5)
    assert res["mAP"]["AP3D_R40"] == pytest.approx(2.5)  # Pedestrian, Cyclist: NaN, left out


def test_equals_the_authors_evaluation_when_their_checkout_is_given():
    # Opt-in oracle (the authors' code is not a package): MSSF_AUTHORS_REPO=/path/to/EricLiuhhh/MSSF.
    # Runs tests/examples/helpers/tj4d_authors_oracle.py in a fresh interpreter (numba's CUDA simulator must be
    # enabled before numba is imported): 3 generated sets of 200 frames, every AP within 0.01.
    import os
    import subprocess
    import sys
    from pathlib import Path

    repo = os.environ.get("MSSF_AUTHORS_REPO")
    if not repo:
        pytest.skip("set MSSF_AUTHORS_REPO to a checkout of EricLiuhhh/MSSF to compare with the authors' eval_tj4d.py")
    pytest.importorskip("numba")
    script = Path(__file__).parents[1] / "helpers" / "tj4d_authors_oracle.py"
    done = subprocess.run([sys.executable, str(script), "--repo", repo, "--frames", "200", "--seeds", "1", "2", "3"],
                          capture_output=True, text=True, timeout=3600)
    assert done.returncode == 0, done.stdout + done.stderr[-2000:]
