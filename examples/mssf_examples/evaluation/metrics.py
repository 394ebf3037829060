"""3D detection evaluation: per-class AP (3D and BEV) with R11 and R40 interpolation, under three protocols.

``evaluate(predictions, ground_truths, class_names, protocol=...)``:

* ``protocol="vod"`` (default): the View-of-Delft devkit (``vod-tudelft``,
  ``vod/evaluation/kitti_official_evaluate.py``) rule for rule -- entire annotated area and driving
  corridor, the kit's 41 score thresholds, 40 px image-box rule, neighbouring classes, two matching
  passes, camera-frame IoU (:mod:`mssf_examples.evaluation.vod`). These are the numbers published VoD
  tables are comparable with.
* ``protocol="tj4d"``: the TJ4DRadSet evaluation of the MSSF authors -- cumulative range bins 0-50 m,
  0-70 m and all, KITTI difficulty -1 ignored, the authors' 41/40 AP (:mod:`mssf_examples.evaluation.tj4d`).
* ``protocol="exact"``: exact interpolated AP with greedy matching on sensor-frame boxes and any
  region functions, for analysis (:mod:`mssf_examples.evaluation.exact`).

``docs/evaluation.md`` lists every rule, its source, and how far the protocols differ.
"""

from __future__ import annotations

import math
from typing import Dict, Mapping, Optional, Sequence

import torch

from mssf_blocks.errors import MSSFError

from ..data.kitti_boxes import camera_boxes_to_sensor
from ..data.kitti_calib import Calibration
from ..data.kitti_labels import KittiObjects
from .exact import (
    DEFAULT_REGIONS,
    RECALL_POINTS,
    RegionFn,
    average_precision,
    corridor_mask,
    driving_corridor,
    evaluate_exact,
    match_frame,
    precision_recall,
    range_region,
)
from .kitti import as_objects
from .tj4d import TJ4D_LOOSE_IOU_THRESHOLDS, TJ4D_REGIONS, TJ4D_STRICT_IOU_THRESHOLDS, evaluate_tj4d
from .vod import VOD_REGIONS, evaluate_vod

__all__ = [
    "PROTOCOLS",
    "VOD_IOU_THRESHOLDS",
    "STRICT_IOU_THRESHOLDS",
    "TJ4D_IOU_THRESHOLDS",
    "TJ4D_STRICT_IOU_THRESHOLDS",
    "TJ4D_LOOSE_IOU_THRESHOLDS",
    "RECALL_POINTS",
    "DEFAULT_REGIONS",
    "VOD_REGIONS",
    "TJ4D_REGIONS",
    "RegionFn",
    "corridor_mask",
    "driving_corridor",
    "range_region",
    "match_frame",
    "precision_recall",
    "average_precision",
    "evaluate",
    "format_table",
]

#: The evaluation protocols of :func:`evaluate`.
PROTOCOLS = ("vod", "tj4d", "exact")
#: VoD / paper IoU thresholds (3D and BEV alike; the VoD kit's ``overlap_0_5`` rows).
VOD_IOU_THRESHOLDS: Dict[str, float] = {"Car": 0.5, "Pedestrian": 0.25, "Cyclist": 0.25}
#: The paper's stricter thresholds (``mAP_str``, Table "fusion block").
STRICT_IOU_THRESHOLDS: Dict[str, float] = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
#: TJ4DRadSet: VoD thresholds plus trucks at 0.5 (the authors' overall mAP).
TJ4D_IOU_THRESHOLDS: Dict[str, float] = {**VOD_IOU_THRESHOLDS, "Truck": 0.5}

_KEYS = ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40")


@torch.no_grad()
def evaluate(
    predictions: Sequence,
    ground_truths: Sequence,
    class_names: Sequence[str],
    iou_thresholds: Optional[Mapping[str, float]] = None,
    regions: Optional[Mapping[str, Optional[RegionFn]]] = None,
    protocol: str = "vod",
) -> Dict[str, Dict[str, Dict[str, float]]]:
    """Per-class 3D and BEV AP (R11 and R40) per region, and their mean over classes.

    Args:
        predictions: one entry per frame. ``"vod"`` / ``"tj4d"``: a
            :class:`~mssf_examples.data.kitti_io.KittiObjects` with scores (a prediction file,
            :func:`~mssf_examples.data.kitti_io.read_labels`), or a dict of sensor-frame ``boxes (K, 7)``,
            ``scores (K,)``, ``labels (K,)`` (0-based into ``class_names``), converted to the camera
            frame with the frame's ``calib`` and ``image_size`` (from this dict or the GT dict).
            ``"exact"``: either (a ``KittiObjects`` is converted to the sensor frame with the GT dict's
            ``calib``, else to the camera-centred frame x forward, y left, z up). Dict labels that run
            ``1..K`` (1-based, OpenPCDet's) are refused.
        ground_truths: one entry per frame: a ``KittiObjects`` (a ``label_2`` file) or a dict of
            sensor-frame ``boxes (G, 7)``, ``labels (G,)`` (outside ``[0, len(class_names))``: not
            evaluated), optional ``ignore (G,)`` bool (ignored rather than missed), and for the
            official protocols ``calib`` (:class:`~mssf_examples.data.kitti_io.Calibration`) and
            ``image_size (H, W)`` -- the 2D boxes of the 40 px / 25 px rules are projected with them,
            so give the full-resolution camera. ``"exact"`` regions may read other keys (``lidar2cam``).
        class_names: names of the classes, in label order (matched case-insensitively to the types
            of KITTI objects).
        iou_thresholds: ``{class name: IoU threshold}`` for 3D and BEV alike; defaults to
            :data:`VOD_IOU_THRESHOLDS` (``"tj4d"``: :data:`TJ4D_IOU_THRESHOLDS`).
        regions: ``"exact"`` only: ``{region name: RegionFn or None}`` (default :data:`DEFAULT_REGIONS`).
            The official protocols have fixed regions: ``entire_area`` and ``driving_corridor``
            (``"vod"``), ``range_0_50``, ``range_0_70``, ``range_all`` (``"tj4d"``).
        protocol: one of :data:`PROTOCOLS`.

    Returns:
        ``results[region][class or "mAP"]`` is a dict with ``AP3D_R11``, ``AP3D_R40``, ``APBEV_R11``,
        ``APBEV_R40`` (percent; NaN for a class without counted GT in the region), and for classes also
        ``num_gt`` (counted GTs) and ``num_pred`` (counted predictions). ``mAP`` averages the classes
        with a defined AP.
    """
    if protocol not in PROTOCOLS:
        raise MSSFError(f"protocol: expected one of {PROTOCOLS}, got {protocol!r}")
    names = list(class_names)
    if not names:
        raise MSSFError("class_names: expected at least one class name, got none")
    default = TJ4D_IOU_THRESHOLDS if protocol == "tj4d" else VOD_IOU_THRESHOLDS
    thresholds = dict(default if iou_thresholds is None else iou_thresholds)
    missing = [c for c in names if c not in thresholds]
    if missing:
        raise MSSFError(f"iou_thresholds: no threshold for classes {missing} (got keys {sorted(thresholds)})")
    for c in names:
        if not 0.0 < float(thresholds[c]) <= 1.0:
            raise MSSFError(f"iou_thresholds[{c!r}]: expected a value in (0, 1], got {thresholds[c]}")
    if len(predictions) != len(ground_truths):
        raise MSSFError(f"predictions, ground_truths: expected one entry per frame in both, got "
                        f"{len(predictions)} and {len(ground_truths)}")
    _check_zero_based(predictions, names)
    if protocol == "exact":
        predictions = [_exact_entry(p, g, names, "predictions", i, True)
                       for i, (p, g) in enumerate(zip(predictions, ground_truths))]
        ground_truths = [_exact_entry(g, p, names, "ground_truths", i, False)
                         for i, (p, g) in enumerate(zip(predictions, ground_truths))]
        regions = dict(DEFAULT_REGIONS if regions is None else regions)
        if not regions:
            raise MSSFError("regions: expected at least one region, got none")
        for region_name, region in regions.items():
            if region is not None and not callable(region):
                raise MSSFError(f"regions[{region_name!r}]: expected a callable or None, got {type(region).__name__}")
        results = evaluate_exact(predictions, ground_truths, names, thresholds, regions)
    else:
        if regions is not None:
            raise MSSFError(f"regions: protocol {protocol!r} has fixed regions "
                            f"{VOD_REGIONS if protocol == 'vod' else tuple(TJ4D_REGIONS)}; "
                            f"custom regions need protocol='exact', got {sorted(regions)}")
        gts = [as_objects(g, p, names, "ground_truths", i, with_scores=False)
               for i, (p, g) in enumerate(zip(predictions, ground_truths))]
        dets = [as_objects(p, g, names, "predictions", i, with_scores=True)
                for i, (p, g) in enumerate(zip(predictions, ground_truths))]
        run = evaluate_vod if protocol == "vod" else evaluate_tj4d
        results = run(dets, gts, names, thresholds)
    for per_class in results.values():
        mean: Dict[str, float] = {}
        for key in _KEYS:
            values = [per_class[c][key] for c in names if not math.isnan(per_class[c][key])]
            mean[key] = sum(values) / len(values) if values else math.nan
        per_class["mAP"] = mean
    return results


def _check_zero_based(predictions: Sequence, names: Sequence[str]) -> None:
    """Prediction dicts whose labels run ``1..K`` with no ``0`` (OpenPCDet's 1-based convention) would
    all be scored as the next class (and the last as none): refused, with the fix."""
    labels = [p["labels"].detach().cpu().long() for p in predictions
              if isinstance(p, Mapping) and isinstance(p.get("labels"), torch.Tensor) and p["labels"].numel()]
    if not labels:
        return
    every = torch.cat([x.reshape(-1) for x in labels])
    lo, hi = int(every.min()), int(every.max())
    if lo >= 1 and hi == len(names):
        raise MSSFError(f"predictions: labels run from {lo} to {hi} with {len(names)} classes {list(names)}: "
                        "1-based (OpenPCDet's pred_labels)? evaluate takes 0-based labels: pass labels - 1")


def _exact_entry(entry, other, names: Sequence[str], what: str, index: int, with_scores: bool):
    """``"exact"`` takes sensor-frame dicts; a :class:`KittiObjects` (a label or prediction file, as the
    other protocols take) is converted: with the frame's ``calib`` (in ``other``) to the sensor frame,
    else to the camera-centred frame (x forward, y left, z up; IoUs do not depend on the frame)."""
    if not isinstance(entry, KittiObjects):
        return entry
    name = f"{what}[{index}]"
    if with_scores and entry.score is None and len(entry):
        raise MSSFError(f"{name}: expected KITTI objects with a score column (16 fields), got none")
    calib = other.get("calib") if isinstance(other, Mapping) else None
    loc, hwl, ry = entry.location.double(), entry.dimensions.double(), entry.rotation_y.double()
    if isinstance(calib, Calibration):
        boxes = camera_boxes_to_sensor(loc, hwl, ry, calib)
    else:  # camera (right, down, forward) -> (forward, left, up); centre of the box, not of its bottom
        h, w, l = hwl.unbind(1) if len(entry) else (hwl[:, 0], hwl[:, 1], hwl[:, 2])
        centre = torch.stack([loc[:, 2], -loc[:, 0], -(loc[:, 1] - h / 2)], 1)
        yaw = torch.atan2(-torch.cos(ry), -torch.sin(ry))  # heading (cos ry, 0, -sin ry) in the new axes
        boxes = torch.cat([centre, torch.stack([l, w, h, yaw], 1)], 1)
    lower = [n.lower() for n in names]
    labels = torch.tensor([lower.index(n.lower()) if n.lower() in lower else -1 for n in entry.names],
                          dtype=torch.long)
    out = {"boxes": boxes.reshape(-1, 7), "labels": labels}
    if with_scores:
        out["scores"] = (entry.score if entry.score is not None else torch.zeros(0)).double()
    return out


# ---------------------------------------------------------------------------------------------------
# Table
# ---------------------------------------------------------------------------------------------------

_REGION_TITLES = {"entire_area": "Entire annotated area", "driving_corridor": "Driving corridor",
                  "range_0_50": "0-50 m", "range_0_70": "0-70 m", "range_all": "All ranges"}
_SHORT = {"Pedestrian": "Ped.", "Cyclist": "Cyc."}


def format_table(
    results: Mapping[str, Mapping] | Mapping[str, Mapping[str, Mapping]],
    metric: str = "AP3D_R11",
    regions: Optional[Sequence[str]] = None,
    digits: int = 2,
) -> str:
    """A plain-text table in the paper's layout: one row per method, per region the classes and mAP.

    Args:
        results: either one :func:`evaluate` result (one row named "method") or ``{method name:
            evaluate result}``.
        metric: which AP to show: ``AP3D_R11`` (VoD's reported number), ``AP3D_R40``, ``APBEV_R11``,
            ``APBEV_R40``.
        regions: region names to show, in order (default: those of the first method).
        digits: decimals.

    Returns:
        The table as a string (NaN shows as ``-``).
    """
    if not results:
        raise MSSFError("results: expected at least one evaluation result, got none")
    first = next(iter(results.values()))
    # A single evaluate() result maps region -> class -> dict of floats.
    single = isinstance(first, Mapping) and "mAP" in first
    methods = {"method": results} if single else dict(results)
    reference = next(iter(methods.values()))
    regions = list(reference) if regions is None else list(regions)
    for name, res in methods.items():
        for region in regions:
            if region not in res:
                raise MSSFError(f"results[{name!r}]: no region {region!r} (has {sorted(res)})")
    classes = [c for c in reference[regions[0]] if c != "mAP"] + ["mAP"]

    def cell(value: float) -> str:
        return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"

    col = max(7, digits + 5)
    name_w = max(len("Method"), *(len(n) for n in methods))
    header1 = " " * name_w
    header2 = "Method".ljust(name_w)
    for region in regions:
        title = f"{_REGION_TITLES.get(region, region)} ({metric})"
        width = len(classes) * (col + 1)
        header1 += " |" + title.center(width)
        header2 += " |" + "".join(" " + _SHORT.get(c, c).rjust(col) for c in classes)
    lines = [header1, header2, "-" * len(header2)]
    for name, res in methods.items():
        row = name.ljust(name_w)
        for region in regions:
            row += " |" + "".join(" " + cell(res[region].get(c, {}).get(metric, math.nan)).rjust(col)
                                  for c in classes)
        lines.append(row)
    return "\n".join(lines)
