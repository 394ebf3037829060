"""``protocol="vod"``: the View-of-Delft devkit's evaluation (``vod-tudelft``,
``vod/evaluation/kitti_official_evaluate.py``), rule for rule, on camera-frame KITTI objects.

The rules (``clean_data`` of the kit; ``docs/evaluation.md`` explains each):

* a GT counts for class ``c`` when its type is ``c`` (case-insensitive); ``Van`` for ``Car`` and
  ``Person_sitting`` for ``Pedestrian`` are ignored GTs (neighbouring classes); anything else, DontCare
  included, is not looked at;
* a GT of class ``c`` is ignored when its image box is at most 40 px high (``bottom - top <= 40``), its
  occlusion is above 4, it carries the caller's ``ignore`` flag, or -- driving corridor -- its location
  (bottom-face centre, camera frame) has ``x < -4``, ``x > 4`` or ``z > 25``;
* a detection is ignored when its image box is under 40 px high (``|bottom - top| < 40``) or -- corridor --
  its location is outside the corridor, *whatever its class*; otherwise it counts for its own class;
* matching: :func:`mssf_examples.evaluation.kitti.threshold_pass` / ``count_pass`` with ``IoU > t``;
* AP: R11 = mean of precision slots 0, 4, ..., 40; R40 = mean of slots 1..40 (``get_m_ap``,
  ``get_m_ap_r40``), in percent.
"""

from __future__ import annotations

from typing import Dict, Mapping, Sequence, Tuple

import numpy as np

from .kitti import NUM_SLOTS, Objects, evaluate_kit

__all__ = ["VOD_REGIONS", "VOD_NEIGHBOURS", "MIN_HEIGHT", "MAX_OCCLUSION", "CORRIDOR", "vod_flags",
           "vod_average_precision", "evaluate_vod"]

#: Region names of the kit's two results (``custom_method`` 0 and 3).
VOD_REGIONS = ("entire_area", "driving_corridor")
#: Neighbouring types whose boxes are ignored (not missed) for a class.
VOD_NEIGHBOURS: Dict[str, str] = {"car": "van", "pedestrian": "person_sitting"}
#: Image-box height limit in pixels (GT: ``<= 40`` ignored; detection: ``< 40`` ignored).
MIN_HEIGHT = 40.0
#: GTs with a larger occlusion level are ignored (VoD's levels are 0-2, so none is).
MAX_OCCLUSION = 4
#: Driving corridor on the camera-frame location: ``(x_min, x_max, z_max)`` in metres.
CORRIDOR = (-4.0, 4.0, 25.0)


def _outside_corridor(location: np.ndarray) -> np.ndarray:
    x, z = location[:, 0], location[:, 2]
    return (x < CORRIDOR[0]) | (x > CORRIDOR[1]) | (z > CORRIDOR[2])


def vod_flags(gt: Objects, dt: Objects, cls: str, region: str) -> Tuple[np.ndarray, np.ndarray]:
    """``ignored_gt (G,)`` and ``ignored_dt (D,)`` (0 counted, 1 ignored, -1 not looked at) for class
    ``cls`` (lower case) in ``region`` (``"entire_area"`` or ``"driving_corridor"``)."""
    corridor = region == "driving_corridor"
    same = gt.names == cls
    neighbour = gt.names == VOD_NEIGHBOURS.get(cls, "\0")
    height = gt.bbox[:, 3] - gt.bbox[:, 1]
    ignore = (gt.occluded > MAX_OCCLUSION) | (height <= MIN_HEIGHT) | gt.ignore
    if corridor:
        ignore |= _outside_corridor(gt.location)
    ignored_gt = np.where(same & ~ignore, 0, np.where(neighbour | same, 1, -1))
    dt_height = np.abs(dt.bbox[:, 3] - dt.bbox[:, 1])
    weak = dt_height < MIN_HEIGHT
    if corridor:
        weak |= _outside_corridor(dt.location)
    ignored_dt = np.where(weak, 1, np.where(dt.names == cls, 0, -1))
    return ignored_gt.astype(np.int64), ignored_dt.astype(np.int64)


def vod_average_precision(precision: np.ndarray) -> Dict[str, float]:
    """R11 and R40 AP (percent) from the kit's 41 precision slots."""
    if precision.shape != (NUM_SLOTS,):
        raise ValueError(f"precision: expected {NUM_SLOTS} slots, got shape {precision.shape}")
    return {"R11": float(precision[0::4].sum() / 11 * 100), "R40": float(precision[1:].sum() / 40 * 100)}


def evaluate_vod(dets: Sequence[Objects], gts: Sequence[Objects], class_names: Sequence[str],
                 thresholds: Mapping[str, float]) -> Dict[str, Dict[str, Dict[str, float]]]:
    """Per-class AP of the VoD kit over the entire annotated area and the driving corridor."""
    return evaluate_kit(dets, gts, class_names, thresholds, VOD_REGIONS, vod_flags, vod_average_precision)
