"""The KITTI-kit machinery behind the official protocols (``protocol="vod"`` and ``"tj4d"``).

Both official evaluations (the View-of-Delft devkit's ``vod/evaluation/kitti_official_evaluate.py`` and
the TJ4DRadSet evaluation of the MSSF authors, ``mmdet3d/evaluation/functional/kitti_utils/eval_tj4d.py``)
are the classic ``kitti_object_eval_python`` algorithm with different rules for which ground truths
(GTs) and detections are ignored. This module is that algorithm, written from its definition
(``docs/evaluation.md`` lists every rule and where it comes from); the protocol modules only supply the
per-frame ignore flags:

* ``ignored_gt`` per GT: ``0`` counts (a miss is a false negative), ``1`` ignored (a detection matching
  it is neutral), ``-1`` never looked at (another class);
* ``ignored_dt`` per detection: ``0`` counts, ``1`` ignored (it can still be matched -- to a GT of *any*
  evaluated class -- and then that GT is neutral too), ``-1`` never looked at.

Boxes are the camera-frame KITTI objects (:class:`Objects`): the BEV IoU is the rotated IoU of the
``(x, z)`` footprints, the 3D IoU adds the overlap along camera ``y`` (:func:`camera_box_ious`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Mapping, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from ..data.kitti_export import kitti_objects
from ..data.kitti_io import Calibration, KittiObjects
from ..models.ops.iou import box_iou_bev_3d
from .exact import check_box_dict

__all__ = ["Objects", "as_objects", "camera_box_ious", "kit_thresholds", "threshold_pass", "count_pass",
           "kit_precision", "evaluate_kit"]

#: Recall sample slots of the kit: 41 score thresholds.
NUM_SLOTS = 41


@dataclass
class Objects:
    """One frame's camera-frame objects as the kit reads them (G objects, numpy float64).

    ``names`` lower-case type strings; ``bbox (G, 4)`` image box ``(left, top, right, bottom)``;
    ``location (G, 3)`` bottom-face centre; ``dimensions (G, 3)`` ``(h, w, l)``; ``rotation_y (G,)``;
    ``occluded``, ``truncated (G,)``; ``score (G,)`` (zeros for labels); ``ignore (G,)`` bool, extra GTs
    to ignore (the caller's ``ignore`` flags).
    """

    names: np.ndarray
    bbox: np.ndarray
    location: np.ndarray
    dimensions: np.ndarray
    rotation_y: np.ndarray
    occluded: np.ndarray
    truncated: np.ndarray
    score: np.ndarray
    ignore: np.ndarray

    def __len__(self) -> int:
        return len(self.names)


def _from_kitti(obj: KittiObjects, ignore: Optional[np.ndarray] = None) -> Objects:
    g = len(obj)
    return Objects(names=np.array([n.lower() for n in obj.names], dtype=object),
                   bbox=obj.boxes_2d.numpy().astype(np.float64).reshape(g, 4),
                   location=obj.location.numpy().astype(np.float64).reshape(g, 3),
                   dimensions=obj.dimensions.numpy().astype(np.float64).reshape(g, 3),
                   rotation_y=obj.rotation_y.numpy().astype(np.float64).reshape(g),
                   occluded=obj.occlusion.numpy().astype(np.float64).reshape(g),
                   truncated=obj.truncation.numpy().astype(np.float64).reshape(g),
                   score=(np.zeros(g) if obj.score is None else obj.score.numpy().astype(np.float64).reshape(g)),
                   ignore=np.zeros(g, dtype=bool) if ignore is None else ignore)


def as_objects(entry, other: Optional[Mapping], class_names: Sequence[str], what: str, index: int,
               with_scores: bool) -> Objects:
    """One frame of ``predictions`` / ``ground_truths`` as :class:`Objects`.

    ``entry`` is a :class:`~mssf_examples.data.kitti_io.KittiObjects` (camera frame, e.g. from
    :func:`~mssf_examples.data.kitti_io.read_labels`), or a dict of sensor-frame ``boxes (K, 7)``, ``labels
    (K,)`` (``scores (K,)`` for predictions, optional ``ignore (K,)`` for GTs), converted with the frame's
    ``calib`` (:class:`~mssf_examples.data.kitti_io.Calibration`) and ``image_size (H, W)``, taken from the
    entry or else from ``other`` (the same frame's entry on the other side).
    """
    name = f"{what}[{index}]"
    if isinstance(entry, KittiObjects):
        if with_scores and entry.score is None and len(entry):
            raise MSSFError(f"{name}: expected KITTI objects with a score column (16 fields), got none")
        return _from_kitti(entry)
    if not isinstance(entry, Mapping):
        raise MSSFError(f"{name}: expected a KittiObjects or a dict of sensor-frame boxes, got {type(entry).__name__}")
    keys = ("boxes", "scores", "labels") if with_scores else ("boxes", "labels")
    check_box_dict(entry, name, keys, optional=() if with_scores else ("ignore",))
    boxes = entry["boxes"]
    calib = entry.get("calib", other.get("calib") if isinstance(other, Mapping) else None)
    size = entry.get("image_size", other.get("image_size") if isinstance(other, Mapping) else None)
    if not isinstance(calib, Calibration) or size is None or len(tuple(size)) != 2:
        raise MSSFError(f"{name}: sensor-frame boxes need the frame's 'calib' (a Calibration) and 'image_size' "
                        f"(H, W) in this dict or in the same frame's other entry, got calib "
                        f"{type(calib).__name__} and image_size {size!r}")
    labels = entry["labels"].detach().cpu().long()
    evaluated = (labels >= 0) & (labels < len(class_names))
    names = [class_names[int(v)] if ok else "DontCare" for v, ok in zip(labels.tolist(), evaluated.tolist())]
    scores = entry["scores"].detach().cpu().to(torch.float64) if with_scores else None
    obj = kitti_objects(boxes.detach().cpu().to(torch.float64), labels, class_names, calib, tuple(size),
                        scores=scores, truncated=0.0, occluded=0, names=names)
    ignore = entry["ignore"].detach().cpu().bool().numpy() if "ignore" in entry and not with_scores else None
    return _from_kitti(obj, ignore)


def camera_box_ious(dets: Objects, gts: Objects) -> Tuple[np.ndarray, np.ndarray]:
    """``(D, G)`` BEV and 3D IoU of camera-frame KITTI boxes, float64.

    BEV: rotated rectangles in the camera ``(x, z)`` plane, length ``l`` along ``(cos ry, -sin ry)``;
    3D: that intersection area times the overlap of ``[y - h, y]`` along camera ``y`` (KITTI
    ``d3_box_overlap``). Computed with :func:`mssf_examples.models.ops.iou.box_iou_bev_3d` on the equivalent
    z-up boxes ``(x, z, -(y - h/2), l, w, h, -ry)``.
    """
    bev, d3 = np.zeros((len(dets), len(gts))), np.zeros((len(dets), len(gts)))
    # DontCare lines carry sizes of -1: no box, no overlap (they are never matched in 3D / BEV anyway).
    rows = np.flatnonzero((dets.dimensions >= 0).all(axis=1))
    cols = np.flatnonzero((gts.dimensions >= 0).all(axis=1))
    if len(rows) == 0 or len(cols) == 0:
        return bev, d3

    def upright(o: Objects, keep: np.ndarray) -> Tensor:
        h, w, l = (o.dimensions[keep, k] for k in range(3))
        x, y, z = (o.location[keep, k] for k in range(3))
        return torch.from_numpy(np.stack([x, z, -(y - h / 2), l, w, h, -o.rotation_y[keep]], axis=1))

    b, d = box_iou_bev_3d(upright(dets, rows), upright(gts, cols))
    bev[np.ix_(rows, cols)], d3[np.ix_(rows, cols)] = b.numpy(), d.numpy()
    return bev, d3


def kit_thresholds(tp_scores: np.ndarray, num_gt: int) -> np.ndarray:
    """The kit's score thresholds (``get_thresholds``): at most 41, one per recall step of 1/40.

    Walking the true-positive scores from the highest down, the score at position ``i`` (recall
    ``(i + 1) / num_gt``) becomes a threshold unless recall ``(i + 2) / num_gt`` is closer to the
    current level; every threshold advances the level by 1/40, and the last score is always taken.
    """
    scores = np.sort(np.asarray(tp_scores, dtype=np.float64))[::-1]
    out: List[float] = []
    level = 0.0
    n = len(scores)
    for i, score in enumerate(scores):
        left = (i + 1) / num_gt
        right = (i + 2) / num_gt if i < n - 1 else left
        if (right - level) < (level - left) and i < n - 1:
            continue
        out.append(float(score))
        level += 1 / (NUM_SLOTS - 1.0)  # accumulated as the kit does: ties at a level break the same way
    return np.asarray(out, dtype=np.float64)


def threshold_pass(iou: np.ndarray, scores: np.ndarray, ignored_gt: np.ndarray, ignored_dt: np.ndarray,
                   min_iou: float) -> List[float]:
    """Scores of the true positives when each GT (in file order) takes its highest-scored free detection.

    A candidate overlaps the GT by ``IoU > min_iou`` and is not ignored with ``-1``; ties in score go to
    the first detection. A GT or detection flagged ``1`` makes the pair neutral (the detection is used up).
    """
    taken = np.zeros(len(scores), dtype=bool)
    out: List[float] = []
    usable = ignored_dt != -1
    for i in range(len(ignored_gt)):
        if ignored_gt[i] == -1:
            continue
        cand = usable & ~taken & (iou[:, i] > min_iou)
        if not cand.any():
            continue
        j = int(np.argmax(np.where(cand, scores, -np.inf)))
        taken[j] = True
        if ignored_gt[i] == 0 and ignored_dt[j] == 0:
            out.append(float(scores[j]))
    return out


def count_pass(iou: np.ndarray, scores: np.ndarray, ignored_gt: np.ndarray, ignored_dt: np.ndarray,
               min_iou: float, thresholds: np.ndarray) -> np.ndarray:
    """``(T, 3)`` true positives, false positives, false negatives of one frame at every threshold.

    At threshold ``t`` the detections scored ``>= t`` compete; each GT (file order) takes the free counted
    (``0``) detection of *largest* IoU ``> min_iou`` (first on ties), or when there is none the first free
    ignored (``1``) one. A pair with an ignored side is neutral; an unmatched counted GT is a false
    negative; an unmatched counted detection a false positive.
    """
    t_count, d_count = len(thresholds), len(scores)
    out = np.zeros((t_count, 3))
    if d_count == 0:
        out[:, 2] = int((ignored_gt == 0).sum())
        return out
    active = scores[None, :] >= thresholds[:, None]                                  # (T, D)
    taken = np.zeros((t_count, d_count), dtype=bool)
    counted, ignored = ignored_dt == 0, ignored_dt == 1
    rows = np.arange(t_count)
    for i in range(len(ignored_gt)):
        if ignored_gt[i] == -1:
            continue
        cand = active & ~taken & (iou[:, i] > min_iou)[None, :]
        valid, weak = cand & counted[None, :], cand & ignored[None, :]
        has_valid, has_weak = valid.any(axis=1), weak.any(axis=1)
        j = np.where(has_valid, np.argmax(np.where(valid, iou[:, i][None, :], -np.inf), axis=1),
                     np.argmax(weak, axis=1))
        found = has_valid | has_weak
        taken[rows[found], j[found]] = True
        if ignored_gt[i] == 0:
            out[:, 0] += has_valid
            out[:, 2] += ~found
    out[:, 1] = (active & ~taken & counted[None, :]).sum(axis=1)
    return out


def kit_precision(counts: np.ndarray) -> np.ndarray:
    """``(41,)`` precision slots: ``TP / (TP + FP)`` per threshold, running maximum from the right, zeros
    after the last threshold (0 where no detection counts at a threshold; the kit divides 0 by 0 there)."""
    prec = np.zeros(NUM_SLOTS)
    t_count = counts.shape[0]
    denom = counts[:, 0] + counts[:, 1]
    prec[:t_count] = np.where(denom > 0, counts[:, 0] / np.where(denom > 0, denom, 1.0), 0.0)
    prec[:t_count] = np.maximum.accumulate(prec[:t_count][::-1])[::-1]
    return prec


#: ``flags(gt, dt, class_name (lower case), region) -> (ignored_gt (G,), ignored_dt (D,))`` int arrays.
FlagFn = Callable[[Objects, Objects, str, str], Tuple[np.ndarray, np.ndarray]]


def evaluate_kit(
    dets: Sequence[Objects],
    gts: Sequence[Objects],
    class_names: Sequence[str],
    thresholds: Mapping[str, float],
    regions: Sequence[str],
    flags: FlagFn,
    ap_fn: Callable[[np.ndarray], Dict[str, float]],
) -> Dict[str, Dict[str, Dict[str, float]]]:
    """``results[region][class]`` of the kit algorithm: ``ap_fn(precision slots)`` per metric, ``num_gt``
    (counted GTs) and ``num_pred`` (counted detections); NaN APs for a class without counted GTs."""
    ious = [camera_box_ious(d, g) for d, g in zip(dets, gts)]
    results: Dict[str, Dict[str, Dict[str, float]]] = {r: {} for r in regions}
    for cname in class_names:
        cls = cname.lower()
        min_iou = float(thresholds[cname])
        for region in regions:
            frame_flags = [flags(g, d, cls, region) for d, g in zip(dets, gts)]
            num_gt = int(sum(int((ig == 0).sum()) for ig, _ in frame_flags))
            entry: Dict[str, float] = {}
            for m, metric in enumerate(("BEV", "3D")):
                tp_scores: List[float] = []
                for (ig, idt), d, iou in zip(frame_flags, dets, ious):
                    tp_scores += threshold_pass(iou[m], d.score, ig, idt, min_iou)
                if num_gt == 0:
                    aps = {k: float("nan") for k in ap_fn(np.zeros(NUM_SLOTS))}
                else:
                    thr = kit_thresholds(np.asarray(tp_scores), num_gt)
                    counts = np.zeros((len(thr), 3))
                    if len(thr):
                        for (ig, idt), d, iou in zip(frame_flags, dets, ious):
                            counts += count_pass(iou[m], d.score, ig, idt, min_iou, thr)
                    aps = ap_fn(kit_precision(counts))
                entry.update({f"AP{metric}_{k}": v for k, v in aps.items()})
            entry["num_gt"] = num_gt
            entry["num_pred"] = int(sum(int((idt == 0).sum()) for _, idt in frame_flags))
            results[region][cname] = {k: entry[k] for k in sorted(entry, key=_key_order)}
    return results


def _key_order(key: str) -> Tuple[int, str]:
    return (0 if key.startswith("AP3D") else 1 if key.startswith("APBEV") else 2, key)
