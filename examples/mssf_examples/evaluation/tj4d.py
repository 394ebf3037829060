"""``protocol="tj4d"``: the TJ4DRadSet evaluation of the MSSF authors (``EricLiuhhh/MSSF``,
``mmdet3d/evaluation/functional/kitti_utils/eval_tj4d.py`` with the GT difficulty of
``tools/dataset_converters/tj4d_data_utils.py``), on camera-frame KITTI objects.

The rules (``docs/evaluation.md`` explains each):

* classes Car, Pedestrian, Cyclist, Truck matched by type (case-insensitive); no neighbouring classes,
  no DontCare handling for 3D / BEV;
* a GT has a KITTI difficulty (``add_difficulty_to_annos``): ``-1`` when its occlusion is above 2, its
  truncation above 0.5 or its image box at most 25 px high; otherwise a *range bin* from the distance
  ``r = |location|`` of its camera-frame location: ``0`` for ``0 < r <= 50`` m, ``1`` for
  ``50 < r <= 70`` m, ``2`` otherwise;
* the three results are cumulative: level ``L`` counts the GTs with ``0 <= difficulty <= L`` and
  ignores the others of the class -- ``range_0_50`` (L = 0), ``range_0_70`` (L = 1), ``range_all``
  (L = 2); detections are never ignored (any range, any size);
* matching as the VoD kit (:mod:`mssf_examples.evaluation.kitti`), ``IoU > t``;
* IoU sets: every class at 0.5 (``TJ4D_STRICT_IOU_THRESHOLDS``) and at 0.25 (``TJ4D_LOOSE_IOU_THRESHOLDS``);
  the overall mAP takes Car and Truck at 0.5, Pedestrian and Cyclist at 0.25
  (:data:`mssf_examples.evaluation.metrics.TJ4D_IOU_THRESHOLDS`);
* AP ("R40", the authors' ``get_mAP``): the sum of all 41 precision slots divided by 40, in percent --
  slot 0 is included, so a perfect detector scores 102.5; "R11" (``get_mAP11``) is the mean of slots
  0, 4, ..., 40.
"""

from __future__ import annotations

from typing import Dict, Mapping, Sequence, Tuple

import numpy as np

from .kitti import NUM_SLOTS, Objects, evaluate_kit

__all__ = ["TJ4D_CLASSES", "TJ4D_REGIONS", "TJ4D_STRICT_IOU_THRESHOLDS", "TJ4D_LOOSE_IOU_THRESHOLDS",
           "tj4d_difficulty", "tj4d_flags", "tj4d_average_precision", "evaluate_tj4d"]

TJ4D_CLASSES = ("Car", "Pedestrian", "Cyclist", "Truck")
#: Result name -> the largest difficulty counted (cumulative range bins).
TJ4D_REGIONS: Dict[str, int] = {"range_0_50": 0, "range_0_70": 1, "range_all": 2}
#: The authors' two uniform IoU sets.
TJ4D_STRICT_IOU_THRESHOLDS: Dict[str, float] = {c: 0.5 for c in TJ4D_CLASSES}
TJ4D_LOOSE_IOU_THRESHOLDS: Dict[str, float] = {c: 0.25 for c in TJ4D_CLASSES}
#: KITTI "hard" limits of ``add_difficulty_to_annos``: beyond them a GT's difficulty is -1.
MAX_OCCLUSION, MAX_TRUNCATION, MIN_HEIGHT = 2, 0.5, 25.0
#: Upper edges of the range bins in metres.
RANGE_EDGES = (50.0, 70.0)


def tj4d_difficulty(gt: Objects) -> np.ndarray:
    """``(G,)`` int difficulty: -1 (too occluded / truncated / small), else the range bin 0, 1 or 2."""
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    bad = (gt.occluded > MAX_OCCLUSION) | (height <= MIN_HEIGHT) | (gt.truncated > MAX_TRUNCATION)
    r = np.sqrt((gt.location ** 2).sum(axis=1))
    bins = np.where((r > 0) & (r <= RANGE_EDGES[0]), 0, np.where((r > RANGE_EDGES[0]) & (r <= RANGE_EDGES[1]), 1, 2))
    return np.where(bad, -1, bins).astype(np.int64)


def tj4d_flags(gt: Objects, dt: Objects, cls: str, region: str) -> Tuple[np.ndarray, np.ndarray]:
    """``ignored_gt (G,)`` and ``ignored_dt (D,)`` for class ``cls`` (lower case) in ``region``."""
    level = TJ4D_REGIONS[region]
    diff = tj4d_difficulty(gt)
    same = gt.names == cls
    ignore = (diff > level) | (diff == -1) | gt.ignore
    ignored_gt = np.where(same & ~ignore, 0, np.where(same, 1, -1))
    ignored_dt = np.where(dt.names == cls, 0, -1)
    return ignored_gt.astype(np.int64), ignored_dt.astype(np.int64)


def tj4d_average_precision(precision: np.ndarray) -> Dict[str, float]:
    """The authors' R11 (``get_mAP11``) and "R40" (``get_mAP``: 41 slots / 40) AP in percent."""
    if precision.shape != (NUM_SLOTS,):
        raise ValueError(f"precision: expected {NUM_SLOTS} slots, got shape {precision.shape}")
    return {"R11": float(precision[0::4].sum() / 11 * 100), "R40": float(precision.sum() / 40 * 100)}


def evaluate_tj4d(dets: Sequence[Objects], gts: Sequence[Objects], class_names: Sequence[str],
                  thresholds: Mapping[str, float]) -> Dict[str, Dict[str, Dict[str, float]]]:
    """Per-class AP of the authors' TJ4DRadSet evaluation for the three cumulative range bins."""
    return evaluate_kit(dets, gts, class_names, thresholds, tuple(TJ4D_REGIONS), tj4d_flags,
                        tj4d_average_precision)
