"""Oracle test: ``evaluate(protocol="vod")`` against the official View-of-Delft kit (``vod-tudelft``).

The kit's evaluation modules are loaded from the installed package by path: ``import vod`` would run
``vod/__init__.py``, which imports the visualisation stack (k3d, matplotlib) the evaluation never
uses. Nothing of the kit is changed. Release 1.0.3 adds 0.01 rad to one side's ``rotation_y`` inside
``calculate_iou_partly`` (a debugging leftover, removed upstream in commit ae5a21e): ``eval_class``
passes the *detections* as that function's first argument, so the kit turns every detection by
+0.01. The kit's copy of the prediction files is written with ``rotation_y - 0.01`` to cancel it.

Three generated sets of 240 frames each (VoD's tilted radar calibration, cars / pedestrians /
cyclists, vans, DontCare, objects inside and outside the corridor and under 40 px, overlapping
boxes, empty frames, tied scores); every AP (3D and BEV, R11 and R40, both regions) must agree with
the kit's within 0.01.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import sys
import time
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from mssf_examples.evaluation.metrics import evaluate
from mssf_examples.data.kitti_export import kitti_lines, write_kitti_file
from mssf_examples.data.kitti_io import Calibration, parse_labels

pytest.importorskip("numba", reason="the VoD kit needs numba (installed by `make test`)")
if importlib.util.find_spec("vod") is None:
    pytest.skip("vod-tudelft is not installed (`make test` installs it)", allow_module_level=True)

CLASSES = ["Car", "Pedestrian", "Cyclist"]
IMAGE_SIZE = (1216, 1936)
#: A View-of-Delft radar calibration (frame 00549): the radar is pitched by about 6 degrees.
VOD_P2 = [[1495.468642, 0.0, 961.272442, 0.0], [0.0, 1495.468642, 624.89592, 0.0], [0.0, 0.0, 1.0, 0.0]]
VOD_TR = [[-0.013857, -0.9997468, 0.01772762, 0.05283124], [0.10934269, -0.01913807, -0.99381983, 0.98100483],
          [0.99390751, -0.01183297, 0.1095802, 1.44445002]]
#: (l, w, h) mean sizes per generated type.
SIZES = {"Car": (4.0, 1.8, 1.5), "Pedestrian": (0.6, 0.6, 1.75), "Cyclist": (1.9, 0.7, 1.7), "Van": (4.8, 2.0, 2.0),
         "bicycle": (1.7, 0.6, 1.1)}
KIT_ROTATION_OFFSET = 0.01  # vod-tudelft 1.0.3, calculate_iou_partly


def load_kit():
    """The kit's ``kitti_official_evaluate`` and ``evaluation_common`` modules, without ``vod/__init__``."""
    if "_vod_kit_eval" not in sys.modules:
        folder = Path(importlib.util.find_spec("vod").submodule_search_locations[0]) / "evaluation"
        package = types.ModuleType("_vod_kit_eval")
        package.__path__ = [str(folder)]
        sys.modules["_vod_kit_eval"] = package
    return (importlib.import_module("_vod_kit_eval.kitti_official_evaluate"),
            importlib.import_module("_vod_kit_eval.evaluation_common"))


def calibration() -> Calibration:
    return Calibration(P2=torch.tensor(VOD_P2, dtype=torch.float64), R0_rect=torch.eye(3, dtype=torch.float64),
                       Tr_velo_to_cam=torch.tensor(VOD_TR, dtype=torch.float64))


def generate_set(seed: int, num_frames: int = 240):
    """``(gt_lines, det_lines)``: per frame, KITTI label lines and prediction lines (with scores)."""
    rng = np.random.default_rng(seed)
    calib = calibration()
    names_all = list(SIZES)
    gt_frames, det_frames = [], []
    for f in range(num_frames):
        if rng.random() < 0.06:  # empty frame (sometimes still with false positives)
            gt_frames.append([])
            det_frames.append(_false_positives(rng, calib, int(rng.integers(0, 3))))
            continue
        boxes, types_ = [], []
        for _ in range(int(rng.integers(1, 10))):
            kind = rng.choice(names_all, p=[0.36, 0.28, 0.26, 0.05, 0.05])
            r = rng.random()
            if r < 0.2:  # near the corridor edges: x_cam = +-4 m, z_cam = 25 m
                x, y = rng.uniform(15, 30), rng.choice([-1, 1]) * rng.uniform(3.2, 4.8)
            elif r < 0.35:  # far and small: many under 40 px
                x, y = rng.uniform(40, 75), rng.uniform(-12, 12)
            else:
                x, y = rng.uniform(3, 45), rng.uniform(-14, 14)
            boxes.append(_box(rng, kind, x, y))
            types_.append(kind)
            if rng.random() < 0.12:  # an overlapping neighbour
                b = boxes[-1].copy()
                b[:2] += rng.normal(0, 0.5, 2)
                boxes.append(b)
                types_.append(kind)
        boxes_t = torch.tensor(np.array(boxes))
        lines = kitti_lines(boxes_t, torch.zeros(len(boxes), dtype=torch.long), CLASSES, calib, IMAGE_SIZE,
                            truncated=0.0, occluded=0, names=types_)
        occl = rng.integers(0, 3, len(lines))
        lines = [ln.replace(" 0.00 0 ", f" 0.00 {int(o)} ", 1) for ln, o in zip(lines, occl)]
        if rng.random() < 0.15:  # a DontCare region (only the 2D metric uses it)
            lines.append("DontCare -1 -1 -10 800.0 500.0 900.0 600.0 -1 -1 -1 -1000 -1000 -1000 -10")
        gt_frames.append(lines)
        det_frames.append(_detections(rng, calib, boxes, types_))
    return gt_frames, det_frames


def _box(rng, kind, x, y):
    l, w, h = (s * rng.uniform(0.9, 1.1) for s in SIZES[kind])
    return np.array([x, y, -1.4 + h / 2 + rng.normal(0, 0.1), l, w, h, rng.uniform(-math.pi, math.pi)])


def _detections(rng, calib, boxes, types_):
    out_boxes, out_names, scores = [], [], []
    for b, kind in zip(boxes, types_):
        if kind == "bicycle" or rng.random() < 0.15:
            continue
        for dup in range(1 + int(rng.random() < 0.15)):
            d = b.copy()
            d[:3] += rng.normal(0, [0.25, 0.25, 0.12]) * (1 + 0.6 * dup)
            d[3:6] *= rng.uniform(0.85, 1.15, 3)
            d[6] += rng.normal(0, 0.15)
            name = "Car" if kind == "Van" else kind
            if rng.random() < 0.05:
                name = str(rng.choice(CLASSES))
            out_boxes.append(d)
            out_names.append(name)
            scores.append(round(float(rng.uniform(0.2, 1.0) - 0.2 * dup), 2))  # 2 decimals: many ties
    fps = _false_positives(rng, calib, int(rng.integers(0, 4)), as_arrays=True)
    out_boxes += fps[0]
    out_names += fps[1]
    scores += fps[2]
    if not out_boxes:
        return []
    return kitti_lines(torch.tensor(np.array(out_boxes)), torch.zeros(len(out_boxes), dtype=torch.long), CLASSES,
                       calib, IMAGE_SIZE, scores=torch.tensor(scores, dtype=torch.float64), names=out_names)


def _false_positives(rng, calib, n, as_arrays=False):
    boxes, names, scores = [], [], []
    for _ in range(n):
        kind = str(rng.choice(CLASSES))
        boxes.append(_box(rng, kind, rng.uniform(3, 70), rng.uniform(-15, 15)))
        names.append(kind)
        scores.append(round(float(rng.uniform(0.05, 0.7)), 2))
    if as_arrays:
        return boxes, names, scores
    if not boxes:
        return []
    return kitti_lines(torch.tensor(np.array(boxes)), torch.zeros(n, dtype=torch.long), CLASSES, calib, IMAGE_SIZE,
                       scores=torch.tensor(scores, dtype=torch.float64), names=names)


def _shift_rotation(line: str, delta: float) -> str:
    f = line.split(" ")
    f[14] = repr(float(f[14]) + delta)
    return " ".join(f)


def kit_results(gt_frames, det_frames, folder: Path):
    """``{(region, class, metric, rp): AP}`` of the kit on the written files."""
    kit, common = load_kit()
    ids = [f"{i:05d}" for i in range(len(gt_frames))]
    for fid, g, d in zip(ids, gt_frames, det_frames):
        write_kitti_file(folder / "label" / f"{fid}.txt", g)
        write_kitti_file(folder / "det" / f"{fid}.txt", [_shift_rotation(ln, -KIT_ROTATION_OFFSET) for ln in d])
    gt_annos = common.get_label_annotations(folder / "label", ids)
    dt_annos = common.get_label_annotations(folder / "det", ids)
    out = {}
    for method, region in ((0, "entire_area"), (3, "driving_corridor")):
        detail = {}
        kit.get_official_eval_result(gt_annos, dt_annos, [0, 1, 2], pr_detail_dict=detail, custom_method=method)
        for metric, key in (("3D", "3d"), ("BEV", "bev")):
            r11, r40 = kit.get_m_ap(detail[key]), kit.get_m_ap_r40(detail[key])
            for j, cname in enumerate(CLASSES):
                out[(region, cname, metric, "R11")] = float(r11[j, 0, 1])
                out[(region, cname, metric, "R40")] = float(r40[j, 0, 1])
    return out


def our_results(gt_frames, det_frames):
    gts = [parse_labels("\n".join(g)) for g in gt_frames]
    dets = [parse_labels("\n".join(d)) if d else parse_labels("") for d in det_frames]
    dets = [d if d.score is not None else _with_empty_score(d) for d in dets]
    res = evaluate(dets, gts, CLASSES)
    return {(region, cname, metric, rp): res[region][cname][f"AP{metric}_{rp}"]
            for region in ("entire_area", "driving_corridor") for cname in CLASSES
            for metric in ("3D", "BEV") for rp in ("R11", "R40")}


def _with_empty_score(objects):
    import dataclasses

    return dataclasses.replace(objects, score=torch.zeros(len(objects), dtype=torch.float64))


def test_vod_protocol_equals_official_kit(tmp_path, capsys):
    t0 = time.perf_counter()
    worst = []
    for seed in (1, 2, 3):
        gt_frames, det_frames = generate_set(seed)
        theirs = kit_results(gt_frames, det_frames, tmp_path / f"set{seed}")
        ours = our_results(gt_frames, det_frames)
        diffs = {k: abs(ours[k] - theirs[k]) for k in theirs}
        key = max(diffs, key=diffs.get)
        worst.append((seed, diffs[key], key))
        assert all(0.0 < theirs[k] < 100.0 for k in theirs if k[3] == "R40"), "degenerate generated set"
        assert max(diffs.values()) < 0.01, (seed, key, ours[key], theirs[key])
    with capsys.disabled():
        print(f"\nvod kit oracle: max |ours - kit| per set {[(s, round(d, 6)) for s, d, _ in worst]}, "
              f"{time.perf_counter() - t0:.1f} s")


def exact_results(gt_frames, det_frames):
    """``protocol="exact"`` on the same objects as sensor-frame boxes (VoD calibration)."""
    from mssf_examples.data.kitti_io import camera_boxes_to_sensor

    calib = calibration()

    def convert(objects, with_scores):
        keep = [i for i, n in enumerate(objects.names) if n in CLASSES]
        idx = torch.tensor(keep, dtype=torch.long)
        boxes = camera_boxes_to_sensor(objects.location[idx], objects.dimensions[idx], objects.rotation_y[idx], calib)
        out = dict(boxes=boxes, labels=torch.tensor([CLASSES.index(objects.names[i]) for i in keep], dtype=torch.long))
        if with_scores:
            out["scores"] = objects.score[idx] if objects.score is not None else torch.zeros(0, dtype=torch.float64)
        return out

    gts = [convert(parse_labels("\n".join(g)), False) for g in gt_frames]
    dets = [convert(parse_labels("\n".join(d)), True) for d in det_frames]
    res = evaluate(dets, gts, CLASSES, protocol="exact")
    return {(region, cname, metric, rp): res[region][cname][f"AP{metric}_{rp}"]
            for region in ("entire_area", "driving_corridor") for cname in CLASSES
            for metric in ("3D", "BEV") for rp in ("R11", "R40")}


def test_exact_protocol_is_not_the_kit(capsys):
    # The oracle can tell protocols apart: the exact protocol misses the kit by whole AP points here.
    gt_frames, det_frames = generate_set(1)
    ours, exact = our_results(gt_frames, det_frames), exact_results(gt_frames, det_frames)
    diffs = {k: exact[k] - ours[k] for k in ours}
    assert max(abs(v) for v in diffs.values()) > 1.0
    with capsys.disabled():
        for region in ("entire_area", "driving_corridor"):
            print(f"\nexact - vod ({region}): " + ", ".join(
                f"{c} {m} {rp} {diffs[(region, c, m, rp)]:+.2f}" for c in CLASSES for m in ("3D", "BEV")
                for rp in ("R11", "R40")))


def test_kit_rotated_iou_wrong_cases():
    # vod/evaluation/rotate_iou_cpu.py (float32 RRPN code) on boxes (x, z, l, w, ry): identical boxes
    # and a square against itself turned by 90 degrees should give 1; the kit returns 0, 1/3, or values
    # outside [0, 1]. Ours (box_iou_bev on the same footprints) gives 1 everywhere.
    load_kit()
    rot = sys.modules["_vod_kit_eval.rotate_iou_cpu"]

    def kit_iou(a, b):
        return float(rot.rotate_iou_eval(np.array([a], dtype=np.float64), np.array([b], dtype=np.float64), -1)[0, 0])

    def our_iou(a, b):
        to = lambda r: [r[0], r[1], 0.0, r[2], r[3], 1.0, -r[4]]  # noqa: E731  (x, z) plane, yaw = -ry
        from mssf_examples.models.ops.iou import box_iou_bev

        return float(box_iou_bev(torch.tensor([to(a)], dtype=torch.float64), torch.tensor([to(b)], dtype=torch.float64))[0, 0])

    cases = {  # (box a, box b): the kit's value
        "identical, ry 0.3": ([0, 10, 4, 2, 0.3], [0, 10, 4, 2, 0.3], 0.0),
        "identical, ry 1.0": ([5, 20, 4.2, 1.8, 1.0], [5, 20, 4.2, 1.8, 1.0], 1 / 3),
        "square +90 deg, ry 0.3": ([0, 10, 2, 2, 0.3], [0, 10, 2, 2, 0.3 + math.pi / 2], 1 / 3),
        "square +90 deg, ry 2.5": ([3, 15, 2, 2, 2.5], [3, 15, 2, 2, 2.5 + math.pi / 2], -6.6634),
        "square +90 deg, ry 2.6": ([3, 15, 2, 2, 2.6], [3, 15, 2, 2, 2.6 + math.pi / 2], -12.0509),
    }
    for name, (a, b, kit_value) in cases.items():
        assert kit_iou(a, b) == pytest.approx(kit_value, abs=1e-3), name
        assert our_iou(a, b) == pytest.approx(1.0, abs=1e-9), name
    # A generic pair agrees to float32 rounding (1 m shift along the length: 3 / 5 = 0.6).
    assert kit_iou([0, 10, 4, 2, 0.0], [1, 10, 4, 2, 0.0]) == pytest.approx(0.6, abs=1e-6)
