"""Tests for ``protocol="exact"`` of ``mssf_examples.evaluation.metrics`` against hand-worked precision-recall curves."""

from __future__ import annotations

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.evaluation.metrics import (
    RECALL_POINTS,
    STRICT_IOU_THRESHOLDS,
    TJ4D_IOU_THRESHOLDS,
    VOD_IOU_THRESHOLDS,
    average_precision,
    corridor_mask,
    driving_corridor,
    format_table,
    match_frame,
    precision_recall,
    range_region,
)
from mssf_examples.evaluation.metrics import evaluate as _evaluate

CLASSES = ["Car", "Pedestrian", "Cyclist"]
ENTIRE = {"entire_area": None}
KEYS = ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40")


def evaluate(*args, **kwargs):
    """Every test here is about the exact protocol (the default is the official VoD one)."""
    return _evaluate(*args, protocol="exact", **kwargs)


def box(x, y, size=2.0, z=0.0, height=2.0, yaw=0.0):
    return [x, y, z, size, size, height, yaw]


def preds(boxes, scores, labels):
    return {
        "boxes": torch.tensor(boxes, dtype=torch.float64).reshape(-1, 7),
        "scores": torch.tensor(scores, dtype=torch.float64),
        "labels": torch.tensor(labels, dtype=torch.long),
    }


def gts(boxes, labels, **extra):
    out = {"boxes": torch.tensor(boxes, dtype=torch.float64).reshape(-1, 7),
           "labels": torch.tensor(labels, dtype=torch.long)}
    out.update(extra)
    return out


def assert_ap(entry, expected, keys=KEYS):
    for key in keys:
        assert entry[key] == pytest.approx(expected, abs=1e-9), key


# Axis-aligned 2 x 2 x 2 boxes shifted along x by d: intersection 2 (2 - d) * 2, union 16 - that.
# d = 0.5 -> IoU 6 / 10 = 0.6; d = 1 -> IoU 4 / 12 = 1/3 (3D and BEV alike).
def _hand_case():
    ground_truths = [
        gts([box(0, 0), box(10, 0)], [0, 0]),  # frame 0: A, B
        gts([box(0, 0)], [0]),  # frame 1: C
    ]
    predictions = [
        preds([box(0.5, 0), box(0, 0), box(10, 0)], [0.9, 0.8, 0.6], [0, 0, 0]),  # p1 (A, IoU .6), p2 (A, IoU 1), p4 (B)
        preds([box(1.0, 0)], [0.7], [0]),  # p3 (C, IoU 1/3)
    ]
    return predictions, ground_truths


def test_hand_worked_case_threshold_0_5():
    # Greedy by score: p1 (0.9) takes A although p2 (0.8) overlaps A better; p2 is then a duplicate.
    #   score : 0.9  0.8  0.7  0.6
    #   TP/FP : TP   FP   FP   TP       (p3 IoU 1/3 < 0.5)
    #   prec  : 1    1/2  1/3  1/2
    #   recall: 1/3  1/3  1/3  2/3
    # interpolated p(r) = 1 for r <= 1/3, 1/2 for 1/3 < r <= 2/3, 0 above.
    # AP11: r = 0, .1, .2, .3 -> 1; .4, .5, .6 -> .5; .7 .. 1 -> 0  => (4 + 1.5) / 11 = 50 %
    # AP40: k/40 <= 1/3 for k = 1..13 -> 1; k = 14..26 -> .5  => (13 + 6.5) / 40 = 48.75 %
    predictions, ground_truths = _hand_case()
    res = evaluate(predictions, ground_truths, ["Car"], {"Car": 0.5}, ENTIRE)["entire_area"]
    assert res["Car"]["num_gt"] == 3 and res["Car"]["num_pred"] == 4
    for metric in ("3D", "BEV"):
        assert res["Car"][f"AP{metric}_R11"] == pytest.approx(50.0, abs=1e-9)
        assert res["Car"][f"AP{metric}_R40"] == pytest.approx(48.75, abs=1e-9)
    assert res["mAP"]["AP3D_R40"] == pytest.approx(48.75, abs=1e-9)


def test_hand_worked_case_threshold_0_25():
    # Now p3 (IoU 1/3) is a TP:
    #   TP/FP : TP   FP   TP   TP
    #   prec  : 1    1/2  2/3  3/4
    #   recall: 1/3  1/3  2/3  1
    # p(r) = 1 for r <= 1/3, 3/4 above.
    # AP11: 4 * 1 + 7 * .75 = 9.25 -> 9.25 / 11 = 84.0909...%
    # AP40: 13 * 1 + 27 * .75 = 33.25 -> 83.125 %
    predictions, ground_truths = _hand_case()
    res = evaluate(predictions, ground_truths, ["Car"], {"Car": 0.25}, ENTIRE)["entire_area"]["Car"]
    for metric in ("3D", "BEV"):
        assert res[f"AP{metric}_R11"] == pytest.approx(925.0 / 11.0, abs=1e-9)
        assert res[f"AP{metric}_R40"] == pytest.approx(83.125, abs=1e-9)


def test_3d_and_bev_differ_by_height_offset():
    # Same footprint, z shifted by 1.2: 3D IoU = 4 * 0.8 / (16 - 3.2) = 0.25 < 0.5, BEV IoU = 1.
    res = evaluate([preds([box(0, 0, z=1.2)], [0.9], [0])], [gts([box(0, 0)], [0])], ["Car"],
                   {"Car": 0.5}, ENTIRE)["entire_area"]["Car"]
    assert res["AP3D_R11"] == 0.0 and res["AP3D_R40"] == 0.0
    assert res["APBEV_R11"] == pytest.approx(100.0) and res["APBEV_R40"] == pytest.approx(100.0)


def test_perfect_predictions_give_100():
    ground_truths = [gts([box(0, 0), box(5, 5, yaw=0.3)], [0, 1]), gts([box(-3, 2, size=1.0)], [2])]
    predictions = [preds([box(0, 0), box(5, 5, yaw=0.3)], [0.3, 0.9], [0, 1]),
                   preds([box(-3, 2, size=1.0)], [0.5], [2])]
    res = evaluate(predictions, ground_truths, CLASSES, VOD_IOU_THRESHOLDS, ENTIRE)["entire_area"]
    for name in CLASSES + ["mAP"]:
        assert_ap(res[name], 100.0)


def test_no_predictions_give_0():
    ground_truths = [gts([box(0, 0)], [0]), gts([box(3, 3)], [0])]
    predictions = [preds([], [], []), preds([], [], [])]
    res = evaluate(predictions, ground_truths, ["Car"], {"Car": 0.5}, ENTIRE)["entire_area"]
    assert_ap(res["Car"], 0.0)
    assert res["Car"]["num_pred"] == 0


def test_wrong_class_does_not_count():
    # A perfect box labelled Pedestrian on a Car GT: Car AP 0, Pedestrian has no GT (NaN) and mAP
    # averages only the classes with GT.
    res = evaluate([preds([box(0, 0)], [0.9], [1])], [gts([box(0, 0)], [0])], CLASSES,
                   VOD_IOU_THRESHOLDS, ENTIRE)["entire_area"]
    assert_ap(res["Car"], 0.0)
    assert all(math.isnan(res["Pedestrian"][k]) for k in KEYS)
    assert res["Pedestrian"]["num_pred"] == 1 and res["Pedestrian"]["num_gt"] == 0
    assert_ap(res["mAP"], 0.0)


def test_frame_without_gt():
    # Frame 1 has no GT: its prediction is a false positive.
    # High-scored FP first: (FP, TP) -> precision (0, 1/2), recall (0, 1) -> p(r) = 1/2 everywhere -> 50.
    ground_truths = [gts([box(0, 0)], [0]), gts([], [])]
    res = evaluate([preds([box(0, 0)], [0.9], [0]), preds([box(4, 4)], [0.95], [0])], ground_truths,
                   ["Car"], {"Car": 0.5}, ENTIRE)["entire_area"]["Car"]
    assert_ap(res, 50.0)
    # Low-scored FP last: (TP, FP) -> precision 1 at recall 1 -> 100.
    res = evaluate([preds([box(0, 0)], [0.9], [0]), preds([box(4, 4)], [0.5], [0])], ground_truths,
                   ["Car"], {"Car": 0.5}, ENTIRE)["entire_area"]["Car"]
    assert_ap(res, 100.0)


def test_tied_scores_enter_together():
    # One GT, a TP and an FP with the same score, the TP listed first: a threshold cannot separate them,
    # so the only PR point is (precision 1/2, recall 1) -> AP 50 (not 100).
    res = evaluate([preds([box(0, 0), box(9, 9)], [0.5, 0.5], [0, 0])], [gts([box(0, 0)], [0])],
                   ["Car"], {"Car": 0.5}, ENTIRE)["entire_area"]["Car"]
    assert_ap(res, 50.0)


def test_ignored_gt_makes_matching_prediction_neutral():
    # GT 0 ignored (e.g. DontCare-like): its perfect prediction (score .9) is neither TP nor FP, the
    # valid GT's prediction (.8) is a TP -> 100. Without the ignore flag: (TP, TP) over 2 GT -> 100 too,
    # so also check num_gt, and an FP on an ignored GT's duplicate.
    ground_truths = [gts([box(0, 0), box(10, 0)], [0, 0], ignore=torch.tensor([True, False]))]
    predictions = [preds([box(0, 0), box(10, 0), box(0.5, 0)], [0.9, 0.8, 0.95], [0, 0, 0])]
    # Order: .95 (ignored GT, IoU .6 -> neutral), .9 (ignored GT already taken -> FP), .8 TP.
    # -> (FP, TP): precision (0, 1/2), recall (0, 1) -> AP 50.
    res = evaluate(predictions, ground_truths, ["Car"], {"Car": 0.5}, ENTIRE)["entire_area"]["Car"]
    assert res["num_gt"] == 1
    assert_ap(res, 50.0)


def test_region_filtering_hand_case():
    # 4 x 4 x 2 boxes; a 1 m lateral shift gives IoU 12 / 20 = 0.6 >= 0.5.
    # Driving corridor without a transform: |y| <= 4 and x <= 25.
    #   GT1 (10, 0)    inside       p_a (10, 0)    .90  inside
    #   GT2 (10, 6)    outside      p_b (10, 6)    .80  outside -> dropped in DC
    #   GT3 (30, 0)    outside      p_d (30, 0)    .60  outside -> dropped in DC
    #   GT4 (10, -4.5) outside      p_c (10, -3.5) .95  inside, IoU .6 with GT4 -> neutral in DC
    #                               p_e (15, 0)    .85  inside, no GT -> FP
    big = dict(size=4.0)
    ground_truths = [gts([box(10, 0, **big), box(10, 6, **big), box(30, 0, **big), box(10, -4.5, **big)],
                         [0, 0, 0, 0])]
    predictions = [preds([box(10, 0, **big), box(10, 6, **big), box(30, 0, **big), box(10, -3.5, **big),
                          box(15, 0, **big)], [0.9, 0.8, 0.6, 0.95, 0.85], [0, 0, 0, 0, 0])]
    res = evaluate(predictions, ground_truths, ["Car"], {"Car": 0.5},
                   {"entire_area": None, "driving_corridor": driving_corridor})
    # Entire area: .95 TP, .9 TP, .85 FP, .8 TP, .6 TP
    #   prec 1, 1, 2/3, 3/4, 4/5; recall 1/4, 1/2, 1/2, 3/4, 1 -> p(r) = 1 for r <= 1/2, 4/5 above.
    #   AP11: 6 * 1 + 5 * .8 = 10 -> 90.909...; AP40: 20 * 1 + 20 * .8 = 36 -> 90.
    eaa = res["entire_area"]["Car"]
    assert eaa["num_gt"] == 4 and eaa["num_pred"] == 5
    assert eaa["AP3D_R11"] == pytest.approx(1000.0 / 11.0, abs=1e-9)
    assert eaa["AP3D_R40"] == pytest.approx(90.0, abs=1e-9)
    # Driving corridor: one valid GT (GT1); counted .95 neutral, .9 TP, .85 FP -> precision 1 at
    # recall 1 -> 100. (Dropping GT4 instead of ignoring it would make .95 an FP first -> 50.)
    dc = res["driving_corridor"]["Car"]
    assert dc["num_gt"] == 1 and dc["num_pred"] == 3
    assert_ap(dc, 100.0)


def test_corridor_mask_default_and_exact_transform():
    boxes = torch.tensor([box(10, 0), box(10, 4.0), box(10, -4.2), box(25.0, 1), box(26, 0), box(3, -3.9)],
                         dtype=torch.float64)
    assert corridor_mask(boxes).tolist() == [True, True, False, True, False, True]
    # A VoD-like sensor -> camera transform: x_cam = -y, y_cam = -z, z_cam = x, plus a translation
    # of the camera origin of (0.2, 0.1, -1.0) in camera coordinates.
    m = torch.tensor([[0.0, -1.0, 0.0, 0.2],
                      [0.0, 0.0, -1.0, 0.1],
                      [1.0, 0.0, 0.0, -1.0],
                      [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)
    # x_cam = -y + 0.2, z_cam = x - 1:
    #   (10, 0) -> (0.2, 9) in; (10, 4) -> (-3.8, 9) in; (10, -4.2) -> (4.4, 9) out;
    #   (25, 1) -> (-0.8, 24) in; (26, 0) -> (0.2, 25) in; (3, -3.9) -> (4.1, 2) out.
    assert corridor_mask(boxes, m).tolist() == [True, True, False, True, True, False]
    assert corridor_mask(boxes, m[:3]).tolist() == [True, True, False, True, True, False]
    frame = {"lidar2cam": m}
    assert driving_corridor(boxes, frame).tolist() == [True, True, False, True, True, False]


def test_range_region():
    boxes = torch.tensor([box(-1, 0), box(0, 0), box(70, 0), box(70.5, 0)], dtype=torch.float64)
    assert range_region(0.0, 70.0)(boxes, {}).tolist() == [False, True, True, False]


def test_match_frame_outcomes():
    # Rows: predictions, columns: GT (second GT ignored).
    iou = torch.tensor([[0.7, 0.0], [0.6, 0.0], [0.0, 0.5], [0.0, 0.49]], dtype=torch.float64)
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6])
    out = match_frame(iou, scores, torch.tensor([False, True]), 0.5)
    # 0.9 -> TP; 0.8 -> GT0 taken -> FP; 0.7 -> ignored GT at IoU 0.5 (>=) -> neutral; 0.6 -> FP.
    assert out.tolist() == [1, 0, -1, 0]


def test_precision_recall_and_average_precision_by_hand():
    precision, recall = precision_recall(torch.tensor([0.9, 0.1, 0.5]), torch.tensor([True, True, False]), 4)
    # Sorted .9 TP, .5 FP, .1 TP: precision 1, 1/2, 2/3; recall 1/4, 1/4, 1/2.
    torch.testing.assert_close(precision, torch.tensor([1.0, 0.5, 2.0 / 3.0], dtype=torch.float64))
    torch.testing.assert_close(recall, torch.tensor([0.25, 0.25, 0.5], dtype=torch.float64))
    # AP11: r = 0, .1, .2 -> 1; .3, .4, .5 -> 2/3; rest 0 -> (3 + 2) / 11.
    assert average_precision(precision, recall, "R11") == pytest.approx(500.0 / 11.0)
    # Recall 3/10 computed as 0.30000000000000004 or 0.29999999999999993 must still reach r = 0.3.
    p = torch.tensor([1.0], dtype=torch.float64)
    r = torch.tensor([3 * 0.1 - 1e-16], dtype=torch.float64)
    assert average_precision(p, r, "R11") == pytest.approx(400.0 / 11.0)
    assert RECALL_POINTS["R40"][0] == pytest.approx(1 / 40) and len(RECALL_POINTS["R40"]) == 40
    assert average_precision(torch.zeros(0), torch.zeros(0), "R40") == 0.0


def test_threshold_tables():
    assert VOD_IOU_THRESHOLDS == {"Car": 0.5, "Pedestrian": 0.25, "Cyclist": 0.25}
    assert STRICT_IOU_THRESHOLDS == {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
    assert TJ4D_IOU_THRESHOLDS["Truck"] == 0.5


def test_format_table_layout():
    predictions, ground_truths = _hand_case()
    res = evaluate(predictions, ground_truths, CLASSES, VOD_IOU_THRESHOLDS)
    table = format_table({"MSSF-V": res, "baseline": res}, metric="AP3D_R40")
    lines = table.splitlines()
    assert "Entire annotated area" in lines[0] and "Driving corridor" in lines[0]
    assert lines[1].split() == ["Method", "|", "Car", "Ped.", "Cyc.", "mAP", "|", "Car", "Ped.", "Cyc.", "mAP"]
    row = lines[3].replace("|", " ").split()
    # Car 48.75 at threshold 0.5; no Pedestrian / Cyclist GT -> "-"; mAP = Car.
    assert row[:5] == ["MSSF-V", "48.75", "-", "-", "48.75"]
    assert lines[4].startswith("baseline")
    single = format_table(res)
    assert single.splitlines()[3].startswith("method")


def test_bad_inputs():
    p, g = _hand_case()
    with pytest.raises(MSSFError, match="one entry per frame"):
        evaluate(p[:1], g, ["Car"])
    with pytest.raises(MSSFError, match="scores"):
        evaluate([{"boxes": p[0]["boxes"], "labels": p[0]["labels"]}, p[1]], g, ["Car"])
    with pytest.raises(MSSFError, match="Truck"):
        evaluate(p, g, ["Car", "Truck"], VOD_IOU_THRESHOLDS)
    with pytest.raises(MSSFError, match="labels"):
        bad = dict(g[0], labels=torch.zeros(5, dtype=torch.long))
        evaluate(p, [bad, g[1]], ["Car"])
    with pytest.raises(MSSFError, match="bool mask"):
        evaluate(p, g, ["Car"], regions={"r": lambda boxes, frame: boxes[:, 0]})
    with pytest.raises(MSSFError, match="lidar2cam"):
        corridor_mask(torch.zeros(1, 7), torch.eye(3))
