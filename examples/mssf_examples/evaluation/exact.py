"""``protocol="exact"``: exact interpolated AP with greedy matching on sensor-frame boxes.

Kept for analysis next to the official protocols (:mod:`mssf_examples.evaluation.vod`,
:mod:`mssf_examples.evaluation.tj4d`); ``docs/evaluation.md`` lists how it differs from them.

* **Boxes** are ``(x, y, z, dx, dy, dz, yaw)`` in the sensor frame (``z`` the centre, yaw about +z);
  overlaps are :func:`mssf_examples.models.ops.iou.box_iou_3d` / :func:`~mssf_examples.models.ops.iou.box_iou_bev`.
* **Matching**, per frame and class: predictions in descending score order; each takes the unmatched
  valid ground truth (GT) of highest IoU and is a true positive (TP) when that IoU is
  ``>= threshold``. Otherwise, if it overlaps an unmatched *ignored* GT by ``>= threshold``, it
  consumes that GT and counts as neither TP nor false positive (FP); otherwise it is an FP.
* **Regions**: a GT whose box centre is outside the region becomes an ignored GT; a prediction whose
  centre is outside the region is dropped. With ``region=None`` (entire annotated area) every GT and
  prediction counts.
* **Precision-recall**: all TP/FP predictions of a class across frames, swept by descending score
  (tied scores enter together, as one threshold); recall = TP / number of valid GT.
* **AP**: interpolated precision ``p(r) = max{precision_k : recall_k >= r}`` (0 when no point reaches
  ``r``), averaged over ``r in {0, 0.1, ..., 1}`` (R11) or ``r in {1/40, 2/40, ..., 1}`` (R40), times 100.

Classes without any valid GT in a region get AP = NaN.
"""

from __future__ import annotations

import math
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from ..models.ops.iou import box_iou_bev_3d

__all__ = [
    "RECALL_POINTS",
    "DEFAULT_REGIONS",
    "RegionFn",
    "corridor_mask",
    "driving_corridor",
    "range_region",
    "match_frame",
    "precision_recall",
    "average_precision",
    "check_box_dict",
    "check_frames",
    "evaluate_exact",
]

#: Recall sample points of the two AP definitions.
RECALL_POINTS: Dict[str, Tensor] = {
    "R11": torch.linspace(0.0, 1.0, 11, dtype=torch.float64),
    "R40": torch.arange(1, 41, dtype=torch.float64) / 40.0,
}

#: ``region(boxes (K, 7), frame: dict) -> (K,) bool``; ``frame`` is that frame's ground-truth dict, so
#: a region can read per-frame metadata such as ``frame["lidar2cam"]``.
RegionFn = Callable[[Tensor, Mapping], Tensor]

_METRICS = ("3D", "BEV")


# ---------------------------------------------------------------------------------------------------
# Regions
# ---------------------------------------------------------------------------------------------------


def corridor_mask(
    boxes: Tensor,
    lidar2cam: Optional[Tensor] = None,
    half_width: float = 4.0,
    max_distance: float = 25.0,
) -> Tensor:
    """Which boxes lie in the VoD driving corridor ``-4 m <= x_cam <= 4 m, z_cam <= 25 m``.

    The corridor is defined in the (rectified) camera frame: ``x_cam`` to the right, ``z_cam`` forward.
    The test uses the box centre; the KITTI label location (bottom-face centre) differs from it only
    along the camera's ``y`` axis, so both give the same answer. The bounds are closed, as in the VoD
    kit (which ignores ``x < -4 or x > 4 or z > 25``; the paper writes strict inequalities -- the
    difference has measure zero).

    Args:
        boxes: ``(K, 7)`` sensor-frame boxes ``(x, y, z, dx, dy, dz, yaw)``.
        lidar2cam: ``(4, 4)`` or ``(3, 4)`` sensor-to-camera transform (e.g. KITTI's
            ``R0_rect @ Tr_velo_to_cam``, :attr:`mssf_examples.data.kitti_io.Calibration.sensor_to_camera`).
            ``None`` assumes a camera at the sensor origin looking along +x with the sensor's ``y`` to
            the left (the synthetic scenes): ``x_cam = -y``, ``z_cam = x``, i.e. ``|y| <= 4, x <= 25``.
        half_width: lateral half-width in metres.
        max_distance: forward limit in metres.

    Returns:
        ``(K,)`` bool.
    """
    if not isinstance(boxes, Tensor) or boxes.dim() != 2 or boxes.shape[1] != 7:
        got = tuple(boxes.shape) if isinstance(boxes, Tensor) else type(boxes).__name__
        raise MSSFError(f"boxes: expected shape (K, 7), got {got}")
    centres = boxes[:, :3].to(torch.float64)
    if lidar2cam is None:
        x_cam, z_cam = -centres[:, 1], centres[:, 0]
    else:
        if not isinstance(lidar2cam, Tensor) or tuple(lidar2cam.shape) not in ((4, 4), (3, 4)):
            got = tuple(lidar2cam.shape) if isinstance(lidar2cam, Tensor) else type(lidar2cam).__name__
            raise MSSFError(f"lidar2cam: expected a (4, 4) or (3, 4) tensor, got {got}")
        m = lidar2cam.to(device=boxes.device, dtype=torch.float64)
        cam = centres @ m[:3, :3].T + m[:3, 3]
        x_cam, z_cam = cam[:, 0], cam[:, 2]
    return (x_cam >= -half_width) & (x_cam <= half_width) & (z_cam <= max_distance)


def driving_corridor(boxes: Tensor, frame: Mapping) -> Tensor:
    """:data:`RegionFn` for the VoD driving corridor; uses ``frame["lidar2cam"]`` when present."""
    return corridor_mask(boxes, frame.get("lidar2cam"))


def range_region(x_min: float = 0.0, x_max: float = 70.0) -> RegionFn:
    """A :data:`RegionFn` keeping box centres with ``x_min <= x <= x_max`` (TJ4DRadSet: 0-70 m)."""

    def region(boxes: Tensor, frame: Mapping) -> Tensor:
        return (boxes[:, 0] >= x_min) & (boxes[:, 0] <= x_max)

    return region


#: The two VoD regions: entire annotated area and driving corridor.
DEFAULT_REGIONS: Dict[str, Optional[RegionFn]] = {
    "entire_area": None,
    "driving_corridor": driving_corridor,
}


# ---------------------------------------------------------------------------------------------------
# Matching, precision-recall and AP
# ---------------------------------------------------------------------------------------------------


def match_frame(iou: Tensor, scores: Tensor, gt_ignored: Tensor, threshold: float) -> Tensor:
    """Greedy matching of one frame's predictions of one class.

    Args:
        iou: ``(K, G)`` IoU of the predictions with the ground truths.
        scores: ``(K,)`` prediction scores.
        gt_ignored: ``(G,)`` bool: ignored GTs (outside the region, or marked ``ignore``).
        threshold: a match needs ``IoU >= threshold``.

    Returns:
        ``(K,)`` int8 outcome per prediction: 1 true positive, 0 false positive, -1 ignored (matched an
        ignored GT).
    """
    k, g = iou.shape
    outcome = torch.zeros(k, dtype=torch.int8)
    if k == 0:
        return outcome
    # Stable sort: equal scores keep input order, so the result is deterministic.
    order = torch.sort(scores.detach().cpu().to(torch.float64), descending=True, stable=True).indices
    iou = iou.detach().cpu().to(torch.float64)
    ignored = gt_ignored.detach().cpu().bool()
    taken = torch.zeros(g, dtype=torch.bool)
    for i in order.tolist():
        row = iou[i]
        valid_free = ~taken & ~ignored
        if bool(valid_free.any()):
            best = torch.where(valid_free, row, torch.full_like(row, -1.0)).argmax()
            if float(row[best]) >= threshold:
                taken[best] = True
                outcome[i] = 1
                continue
        ignored_free = ~taken & ignored
        if bool(ignored_free.any()):
            best = torch.where(ignored_free, row, torch.full_like(row, -1.0)).argmax()
            if float(row[best]) >= threshold:
                taken[best] = True
                outcome[i] = -1
    return outcome


def precision_recall(scores: Tensor, is_tp: Tensor, num_gt: int) -> Tuple[Tensor, Tensor]:
    """Precision and recall at every distinct score threshold.

    Args:
        scores: ``(K,)`` scores of the counted (TP or FP) predictions of one class, all frames.
        is_tp: ``(K,)`` bool.
        num_gt: number of valid ground truths (> 0).

    Returns:
        ``precision (T,)`` and ``recall (T,)`` float64, one entry per distinct score, from the highest
        score down (predictions with equal scores enter together).
    """
    if num_gt <= 0:
        raise MSSFError(f"num_gt: expected a positive number of ground truths, got {num_gt}")
    scores = scores.detach().cpu().to(torch.float64)
    order = torch.sort(scores, descending=True, stable=True).indices
    scores, tp = scores[order], is_tp.detach().cpu().bool()[order].to(torch.float64)
    tp_cum = tp.cumsum(0)
    fp_cum = (1.0 - tp).cumsum(0)
    if scores.numel() == 0:
        return scores.new_zeros(0), scores.new_zeros(0)
    # Last index of every run of equal scores: a threshold cannot split a tie.
    last = torch.ones_like(scores, dtype=torch.bool)
    last[:-1] = scores[1:] != scores[:-1]
    tp_cum, fp_cum = tp_cum[last], fp_cum[last]
    return tp_cum / (tp_cum + fp_cum), tp_cum / num_gt


def average_precision(precision: Tensor, recall: Tensor, recall_points: Tensor | str = "R40") -> float:
    """Interpolated AP (in percent) of a precision-recall curve.

    ``AP = 100 * mean_r p(r)`` with ``p(r) = max{precision_k : recall_k >= r}`` and 0 when no point of
    the curve reaches recall ``r``.

    Args:
        precision: ``(T,)`` precision values.
        recall: ``(T,)`` recall values (any order).
        recall_points: ``"R11"``, ``"R40"`` or a 1-d tensor of recall levels.

    Returns:
        AP in ``[0, 100]``.
    """
    if isinstance(recall_points, str):
        if recall_points not in RECALL_POINTS:
            raise MSSFError(f"recall_points: expected one of {sorted(RECALL_POINTS)} or a tensor, "
                            f"got {recall_points!r}")
        recall_points = RECALL_POINTS[recall_points]
    if precision.shape != recall.shape or precision.dim() != 1:
        raise MSSFError(f"precision, recall: expected two 1-d tensors of equal length, got shapes "
                        f"{tuple(precision.shape)} and {tuple(recall.shape)}")
    points = recall_points.to(torch.float64)
    if precision.numel() == 0:
        return 0.0
    p = precision.detach().cpu().to(torch.float64)
    r = recall.detach().cpu().to(torch.float64)
    # A tiny slack keeps recall 0.3 reached when cumsum / num_gt rounds to 0.29999999999999993.
    reached = r[None, :] >= points[:, None] - 1e-12
    interp = torch.where(reached, p[None, :], torch.zeros_like(p)[None, :]).amax(dim=1)
    return float(interp.mean() * 100.0)


# ---------------------------------------------------------------------------------------------------
# Full evaluation
# ---------------------------------------------------------------------------------------------------


def check_box_dict(frame: Mapping, name: str, keys: Sequence[str], optional: Sequence[str] = ()) -> int:
    """Check one frame's dict of ``boxes (K, 7)`` and per-box ``keys[1:]`` / present ``optional`` ``(K,)``.

    ``keys`` must start with ``"boxes"``; ``name`` names the frame in errors (``predictions[3]``).
    Returns ``K``.
    """
    for key in keys:
        if key not in frame:
            raise MSSFError(f"{name}: missing key {key!r} (expected keys {tuple(keys)})")
    boxes = frame["boxes"]
    if not isinstance(boxes, Tensor) or boxes.dim() != 2 or boxes.shape[1] != 7:
        got = tuple(boxes.shape) if isinstance(boxes, Tensor) else type(boxes).__name__
        raise MSSFError(f"{name}['boxes']: expected shape (K, 7), got {got}")
    k = boxes.shape[0]
    for key in tuple(keys[1:]) + tuple(key for key in optional if key in frame):
        v = frame[key]
        if not isinstance(v, Tensor) or tuple(v.shape) != (k,):
            got = tuple(v.shape) if isinstance(v, Tensor) else type(v).__name__
            raise MSSFError(f"{name}[{key!r}]: expected shape ({k},) to match boxes, got {got}")
    return k


def check_frames(predictions: Sequence[Mapping], ground_truths: Sequence[Mapping]) -> None:
    """One dict per frame on both sides, with ``boxes (K, 7)`` and matching ``scores`` / ``labels`` / ``ignore``."""
    if len(predictions) != len(ground_truths):
        raise MSSFError(f"predictions, ground_truths: expected one entry per frame in both, got "
                        f"{len(predictions)} and {len(ground_truths)}")
    for i, frame in enumerate(predictions):
        check_box_dict(frame, f"predictions[{i}]", ("boxes", "scores", "labels"))
    for i, frame in enumerate(ground_truths):
        check_box_dict(frame, f"ground_truths[{i}]", ("boxes", "labels"), optional=("ignore",))


@torch.no_grad()
def evaluate_exact(
    predictions: Sequence[Mapping[str, Tensor]],
    ground_truths: Sequence[Mapping[str, Tensor]],
    names: Sequence[str],
    thresholds: Mapping[str, float],
    regions: Mapping[str, Optional[RegionFn]],
) -> Dict[str, Dict[str, Dict[str, float]]]:
    """``protocol="exact"`` of :func:`mssf_examples.evaluation.metrics.evaluate` (arguments already validated
    there, except the frames); ``results[region][class]``, the mean over classes is added by the caller."""
    check_frames(predictions, ground_truths)
    results: Dict[str, Dict[str, Dict[str, float]]] = {name: {} for name in regions}
    for c, cname in enumerate(names):
        threshold = float(thresholds[cname])
        # Per region and metric: scores and TP flags of the counted predictions, number of valid GT.
        scores: Dict[Tuple[str, str], List[Tensor]] = {(r, m): [] for r in regions for m in _METRICS}
        tps: Dict[Tuple[str, str], List[Tensor]] = {(r, m): [] for r in regions for m in _METRICS}
        num_gt = {r: 0 for r in regions}
        num_pred = {r: 0 for r in regions}
        for pred, gt in zip(predictions, ground_truths):
            pm = pred["labels"] == c
            gm = gt["labels"] == c
            p_boxes, p_scores = pred["boxes"][pm], pred["scores"][pm]
            g_boxes = gt["boxes"][gm].to(p_boxes.dtype)
            g_ignored = gt["ignore"][gm].bool() if "ignore" in gt else torch.zeros(
                g_boxes.shape[0], dtype=torch.bool, device=g_boxes.device)
            # The overlaps do not depend on the region: compute them once per frame and class.
            ious = {}
            if p_boxes.shape[0]:
                ious["BEV"], ious["3D"] = box_iou_bev_3d(p_boxes, g_boxes)
            for region_name, region in regions.items():
                keep = torch.ones(p_boxes.shape[0], dtype=torch.bool, device=p_boxes.device)
                ignored = g_ignored
                if region is not None:
                    keep = _region_mask(region, p_boxes, gt, region_name, "predictions")
                    ignored = g_ignored | ~_region_mask(region, g_boxes, gt, region_name, "ground_truths")
                num_gt[region_name] += int((~ignored).sum())
                num_pred[region_name] += int(keep.sum())
                if not bool(keep.any()):
                    continue
                kept_scores = p_scores[keep]
                for metric in _METRICS:
                    outcome = match_frame(ious[metric][keep], kept_scores, ignored, threshold)
                    counted = outcome >= 0
                    scores[(region_name, metric)].append(kept_scores.detach().cpu()[counted])
                    tps[(region_name, metric)].append(outcome[counted] == 1)
        for region_name in regions:
            entry: Dict[str, float] = {}
            for metric in _METRICS:
                for rp in RECALL_POINTS:
                    key = f"AP{metric}_{rp}"
                    if num_gt[region_name] == 0:
                        entry[key] = math.nan
                    elif not scores[(region_name, metric)]:
                        entry[key] = 0.0
                    else:
                        precision, recall = precision_recall(torch.cat(scores[(region_name, metric)]),
                                                             torch.cat(tps[(region_name, metric)]),
                                                             num_gt[region_name])
                        entry[key] = average_precision(precision, recall, rp)
            entry["num_gt"] = num_gt[region_name]
            entry["num_pred"] = num_pred[region_name]
            results[region_name][cname] = entry
    return results


def _region_mask(region: RegionFn, boxes: Tensor, frame: Mapping, region_name: str, what: str) -> Tensor:
    mask = region(boxes, frame)
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool or tuple(mask.shape) != (boxes.shape[0],):
        got = (f"{mask.dtype} tensor of shape {tuple(mask.shape)}" if isinstance(mask, Tensor)
               else type(mask).__name__)
        raise MSSFError(f"regions[{region_name!r}]: expected a ({boxes.shape[0]},) bool mask for the "
                        f"{what} boxes, got {got}")
    return mask.to(boxes.device)

