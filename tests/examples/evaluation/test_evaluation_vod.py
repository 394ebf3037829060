"""Hand-worked cases for ``protocol="vod"``: one per way the VoD kit differs from exact interpolation.

The numbers are worked out in the comments from the kit's definitions (``docs/evaluation.md``); the
oracle comparison with the kit itself is ``test_evaluation_vod_kit.py``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.evaluation.metrics import evaluate, match_frame
from mssf_examples.evaluation.kitti import (
    _from_kitti,
    camera_box_ious,
    count_pass,
    kit_thresholds,
    threshold_pass,
)
from mssf_examples.evaluation.vod import vod_flags
from mssf_examples.data.kitti_io import Calibration, KittiObjects, camera_boxes_to_sensor
from mssf_examples.models.ops.iou import box_iou_bev

F64 = dict(dtype=torch.float64)


def objects(rows, scores=None):
    """``rows``: ``(type, (left, top, right, bottom), (h, w, l), (x, y, z), ry[, occlusion])``."""
    g = len(rows)
    return KittiObjects(
        names=[r[0] for r in rows], truncation=torch.zeros(g, **F64),
        occlusion=torch.tensor([r[5] if len(r) > 5 else 0 for r in rows], dtype=torch.long),
        alpha=torch.zeros(g, **F64), boxes_2d=torch.tensor([r[1] for r in rows], **F64).reshape(g, 4),
        dimensions=torch.tensor([r[2] for r in rows], **F64).reshape(g, 3),
        location=torch.tensor([r[3] for r in rows], **F64).reshape(g, 3),
        rotation_y=torch.tensor([r[4] for r in rows], **F64).reshape(g),
        score=None if scores is None else torch.tensor(scores, **F64))


TALL = (100.0, 100.0, 200.0, 200.0)  # a 100 px high image box
CAR = (1.5, 2.0, 4.0)


def car(x=0.0, z=10.0, box=TALL, name="Car", ry=0.0, y=1.5):
    return (name, box, CAR, (x, y, z), ry)


def ap(res, region="entire_area", cls="Car"):
    e = res[region][cls]
    return e["AP3D_R11"], e["AP3D_R40"], e["APBEV_R11"], e["APBEV_R40"]


# --- cause 1: the kit's 41 score thresholds -------------------------------------------------------

def test_cause1_perfect_detector_with_40_gts():
    # 40 frames, one car each, detected exactly with distinct scores. get_thresholds takes every TP
    # score (recall (i+1)/40 always reaches the level i/40), so 40 thresholds fill slots 0..39 with
    # precision 1 and slot 40 stays 0: R40 = 39/40 = 97.5, R11 = slots 0, 4, ..., 36 = 10/11 = 90.909.
    scores = [1.0 - 0.01 * i for i in range(40)]
    assert len(kit_thresholds(np.array(scores), 40)) == 40
    gts = [objects([car()]) for _ in range(40)]
    dets = [objects([car()], [s]) for s in scores]
    res = evaluate(dets, gts, ["Car"])
    assert ap(res) == pytest.approx((1000 / 11, 97.5, 1000 / 11, 97.5))
    exact = evaluate([_sensor_pred(d) for d in dets], [_sensor_gt(g) for g in gts], ["Car"], protocol="exact")
    assert exact["entire_area"]["Car"]["AP3D_R40"] == pytest.approx(100.0)


def test_cause1_last_tp_filed_under_the_next_level():
    # 80 GTs, the first 41 detected exactly (precision 1), the rest missed. Thresholds: i = 0 (recall
    # 1/80, level 0), then every odd i (recall 2k/80 = k/40 hits level k/40 exactly, the even i are
    # skipped as the next recall is closer) up to i = 39 (level 20/40), and i = 40 because the last TP is
    # always taken: 22 thresholds. Slot 21 gets precision 1 although recall 41/80 = 0.5125 < 21/40.
    # Kit: R40 = 21/40 = 52.5, R11 = slots 0, 4, ..., 20 = 6/11 = 54.545.
    # Exact: recall 0.5125 reaches the levels 1/40 .. 20/40 (R40 = 50) and 0, 0.1, ..., 0.5 (R11 6/11).
    scores = [1.0 - 0.01 * i for i in range(41)]
    assert len(kit_thresholds(np.array(scores), 80)) == 22
    gts = [objects([car()]) for _ in range(80)]
    dets = [objects([car()], [s]) for s in scores] + [objects([], []) for _ in range(39)]
    res = evaluate(dets, gts, ["Car"])
    assert ap(res) == pytest.approx((600 / 11, 52.5, 600 / 11, 52.5))
    exact = evaluate([_sensor_pred(d) for d in dets], [_sensor_gt(g) for g in gts], ["Car"], protocol="exact")
    assert exact["entire_area"]["Car"]["AP3D_R40"] == pytest.approx(50.0)
    assert exact["entire_area"]["Car"]["AP3D_R11"] == pytest.approx(600 / 11)


# --- cause 2: the 40 px image-box rule ----------------------------------------------------------

def test_cause2_height_rule_flags():
    # GT: ignored when bottom - top <= 40; detection: ignored when |bottom - top| < 40.
    gt = _from_kitti(objects([car(box=(0, 100, 50, 140)), car(box=(0, 100, 50, 140.5)), car(box=(0, 0, 50, 300), y=1)]
                             + [("Car", TALL, CAR, (0, 1.5, 10), 0.0, 5)]))  # occlusion 5 > 4: ignored too
    dt = _from_kitti(objects([car(box=(0, 100, 50, 139.9)), car(box=(0, 100, 50, 140)),
                              car(box=(0, 140, 50, 100))], [0.5, 0.5, 0.5]))
    ig, idt = vod_flags(gt, dt, "car", "entire_area")
    assert ig.tolist() == [1, 0, 0, 1]
    assert idt.tolist() == [1, 0, 0]  # a flipped box counts by its absolute height


def test_cause2_small_detection_neutralises_its_gt():
    # Frame 0: GT A detected by a 30 px high detection (ignored, score 0.9) -> pair neutral.
    # Frame 1: GT B detected normally (score 0.8) -> the only TP; thresholds [0.8] (2 counted GTs).
    # Precision at 0.8 = 1/1 -> slot 0 = 1: R11 = 100/11, R40 = 0.
    # Exact protocol (no height rule): 2 TPs at 0.9 and 0.8, AP 100.
    gts = [objects([car()]), objects([car()])]
    dets = [objects([car(box=(100, 100, 200, 130))], [0.9]), objects([car()], [0.8])]
    res = evaluate(dets, gts, ["Car"])
    assert ap(res) == pytest.approx((100 / 11, 0.0, 100 / 11, 0.0))
    assert res["entire_area"]["Car"]["num_gt"] == 2 and res["entire_area"]["Car"]["num_pred"] == 1


# --- cause 3: IoU on the camera-frame boxes -----------------------------------------------------

def test_cause3_camera_frame_iou_by_hand():
    # Two 4 x 2 m footprints (ry = 0: length along camera x) 1 m apart along x: BEV IoU 6 / 10 = 0.6.
    # Also 0.5 m apart along camera y: height overlap 1.0 of 1.5 m -> 3D IoU 6 / (12 + 12 - 6) = 1/3.
    a = _from_kitti(objects([car(x=0.0)]))
    b = _from_kitti(objects([car(x=1.0, y=2.0)]))
    bev, d3 = camera_box_ious(b, a)
    assert bev[0, 0] == pytest.approx(0.6) and d3[0, 0] == pytest.approx(1 / 3)


def test_cause3_tilted_sensor_frame_gives_another_iou():
    # Pitch the camera by theta about its x axis. Two camera-upright boxes 0.5 m apart along camera y
    # (heading along camera z) have identical (x, z) footprints: the kit's BEV IoU is exactly 1. As
    # sensor-upright boxes (exact protocol) their centres are d sin(theta) apart along the length:
    # IoU = (l - s) / (l + s) with s = 0.5 sin(theta); theta = 6 deg: s = 0.052264, IoU = 0.974205.
    theta = math.radians(6.0)
    perm = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], **F64)
    c, s_ = math.cos(theta), math.sin(theta)
    pitch = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s_], [0.0, s_, c]], **F64)
    tr = torch.cat([pitch @ perm, torch.zeros(3, 1, **F64)], dim=1)
    calib = Calibration(P2=torch.tensor([[1000.0, 0, 960, 0], [0, 1000.0, 600, 0], [0, 0, 1.0, 0]], **F64),
                        R0_rect=torch.eye(3, **F64), Tr_velo_to_cam=tr)
    ry = -math.pi / 2  # heading (cos ry, -sin ry) = +z
    a, b = objects([car(z=15.0, ry=ry)]), objects([car(z=15.0, ry=ry, y=2.0)])
    kit_bev, _ = camera_box_ious(_from_kitti(b), _from_kitti(a))
    assert kit_bev[0, 0] == pytest.approx(1.0)
    sa = camera_boxes_to_sensor(a.location, a.dimensions, a.rotation_y, calib)
    sb = camera_boxes_to_sensor(b.location, b.dimensions, b.rotation_y, calib)
    shift = 0.5 * math.sin(theta)
    assert float(box_iou_bev(sb, sa)[0, 0]) == pytest.approx((4.0 - shift) / (4.0 + shift), abs=1e-9)
    assert (4.0 - shift) / (4.0 + shift) == pytest.approx(0.974205, abs=1e-6)


# --- cause 4: thresholds from a highest-score pass, counts from a largest-overlap pass ----------

def test_cause4_two_matching_passes():
    # GT 1 then GT 2 (file order); detection a (0.9) overlaps GT 1 by 0.6 and GT 2 by 0.7, detection b
    # (0.8) overlaps GT 1 by 0.9. Threshold pass: GT 1 takes the highest score, a -> TP score 0.9; GT 2
    # finds nothing free. Count pass at threshold 0.8: GT 1 takes the largest overlap, b; GT 2 takes a:
    # 2 TPs. Greedy-by-score (exact): a takes its best GT, GT 2 (0.7); b takes GT 1: 2 TPs.
    iou = np.array([[0.6, 0.7], [0.9, 0.0]])
    scores = np.array([0.9, 0.8])
    flags_gt, flags_dt = np.array([0, 0]), np.array([0, 0])
    assert threshold_pass(iou, scores, flags_gt, flags_dt, 0.5) == [0.9]
    counts = count_pass(iou, scores, flags_gt, flags_dt, 0.5, np.array([0.9, 0.8]))
    assert counts.tolist() == [[1, 0, 1], [2, 0, 0]]  # (TP, FP, FN) at 0.9 and 0.8
    greedy = match_frame(torch.tensor(iou), torch.tensor(scores), torch.zeros(2, dtype=torch.bool), 0.5)
    assert greedy.tolist() == [1, 1]


def test_cause4_kit_uses_strict_inequality():
    # IoU exactly at the threshold does not match in the kit (IoU > t); the exact protocol uses >=.
    iou = np.array([[0.5]])
    assert threshold_pass(iou, np.array([0.9]), np.array([0]), np.array([0]), 0.5) == []


# --- cause 5: detections ignored before the class check -----------------------------------------

def test_cause5_small_car_detection_neutralises_a_pedestrian():
    # Pedestrian GT P; a Car detection c only 30 px high (ignored for *every* class, score 0.9) and a
    # Pedestrian detection p (score 0.5), both on P. Threshold pass for Pedestrian: P takes the highest
    # score among non-(-1) detections, c -> neutral, so no TP score, no threshold: AP 0. Without c,
    # p is a TP: thresholds [0.5], slot 0 = 1, R11 = 100/11.
    ped = ("Pedestrian", TALL, (1.7, 0.6, 0.6), (0.0, 1.5, 10.0), 0.0)
    small_car = ("Car", (100.0, 100.0, 200.0, 130.0), (1.7, 0.6, 0.6), (0.0, 1.5, 10.0), 0.0)
    gts = [objects([ped])]
    with_car = evaluate([objects([small_car, ped], [0.9, 0.5])], gts, ["Car", "Pedestrian"])
    without = evaluate([objects([ped], [0.5])], gts, ["Car", "Pedestrian"])
    assert ap(with_car, cls="Pedestrian") == pytest.approx((0.0, 0.0, 0.0, 0.0))
    assert ap(without, cls="Pedestrian") == pytest.approx((100 / 11, 0.0, 100 / 11, 0.0))


def test_cause5_corridor_detection_of_another_class_is_ignored_not_dropped():
    # Corridor: a Cyclist detection at x = 4.5 m is outside (x > 4), so ignored_dt = 1 even for Car;
    # x = 4.0 and z = 25.0 are inside (closed bounds).
    dt = _from_kitti(objects([("Cyclist", TALL, CAR, (4.5, 1.5, 10), 0.0), car(x=4.0, z=25.0),
                              car(x=-4.01), car(z=25.01)], [0.5] * 4))
    gt = _from_kitti(objects([car(), car(x=4.0, z=25.0), car(x=-4.01), ("Van", TALL, CAR, (0, 1.5, 10), 0.0),
                              ("Person_sitting", TALL, CAR, (0, 1.5, 10), 0.0), ("DontCare", TALL, CAR, (0, 1.5, 10), 0.0)]))
    ig, idt = vod_flags(gt, dt, "car", "driving_corridor")
    assert idt.tolist() == [1, 0, 1, 1]
    assert ig.tolist() == [0, 0, 1, 1, -1, -1]
    ig_p, _ = vod_flags(gt, dt, "pedestrian", "entire_area")
    assert ig_p.tolist() == [-1, -1, -1, -1, 1, -1]


# --- interface ----------------------------------------------------------------------------------

def test_sensor_dicts_need_calibration():
    gts = [dict(boxes=torch.zeros(1, 7, **F64), labels=torch.zeros(1, dtype=torch.long))]
    preds = [dict(boxes=torch.zeros(0, 7, **F64), labels=torch.zeros(0, dtype=torch.long), scores=torch.zeros(0))]
    with pytest.raises(MSSFError, match="calib"):
        evaluate(preds, gts, ["Car"])
    with pytest.raises(MSSFError, match="fixed regions"):
        evaluate(preds, gts, ["Car"], regions={"entire_area": None})
    with pytest.raises(MSSFError, match="protocol"):
        evaluate(preds, gts, ["Car"], protocol="kitti")
    with pytest.raises(MSSFError, match="score column"):
        evaluate([objects([car()])], [objects([car()])], ["Car"])


def test_sensor_dicts_equal_their_kitti_objects():
    # The same boxes given as sensor dicts (converted with the frame's calibration) or as the KITTI
    # objects kitti_objects() writes give the same AP.
    from mssf_examples.data.kitti_export import kitti_objects

    calib = _calib()
    g = torch.tensor([[10.0, 0.0, -0.5, 4.0, 1.8, 1.5, 0.2], [20.0, 3.0, -0.5, 0.6, 0.6, 1.7, 0.0]], **F64)
    p = g + torch.tensor([[0.3, 0.1, 0.0, 0.0, 0.0, 0.0, 0.05], [0.1, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0]], **F64)
    labels, scores = torch.tensor([0, 1]), torch.tensor([0.9, 0.7], **F64)
    frame = dict(calib=calib, image_size=(1216, 1936))
    a = evaluate([dict(boxes=p, labels=labels, scores=scores)], [dict(boxes=g, labels=labels, **frame)],
                 ["Car", "Pedestrian"])
    b = evaluate([kitti_objects(p, labels, ["Car", "Pedestrian"], calib, (1216, 1936), scores=scores)],
                 [kitti_objects(g, labels, ["Car", "Pedestrian"], calib, (1216, 1936))], ["Car", "Pedestrian"])
    assert a == b and a["entire_area"]["mAP"]["AP3D_R11"] == pytest.approx(100 / 11)


def _calib():
    tr = torch.tensor([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]], **F64)
    return Calibration(P2=torch.tensor([[1495.0, 0, 961, 0], [0, 1495.0, 625, 0], [0, 0, 1.0, 0]], **F64),
                       R0_rect=torch.eye(3, **F64), Tr_velo_to_cam=tr)


def _sensor_gt(obj):
    boxes = camera_boxes_to_sensor(obj.location, obj.dimensions, obj.rotation_y, _calib())
    return dict(boxes=boxes, labels=torch.zeros(len(obj), dtype=torch.long))


def _sensor_pred(obj):
    return dict(_sensor_gt(obj), scores=obj.score)
