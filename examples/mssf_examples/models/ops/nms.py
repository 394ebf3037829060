"""Rotated bird's-eye-view non-maximum suppression.

Greedy NMS: visit boxes in descending score order (ties: the lower input index first, via a stable
sort) and keep a box unless its rotated BEV IoU (:func:`mssf_examples.models.ops.iou.box_iou_bev`) with an
already kept box is strictly greater than ``iou_threshold``.

:func:`nms_bev` computes the IoU matrix once and suppresses with one boolean row operation per kept
box; :func:`nms_bev_reference` is the plain Python loop it is tested against.
"""

from __future__ import annotations

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.errors import MSSFError

from .iou import box_iou_bev

__all__ = ["nms_bev", "nms_bev_reference", "batched_nms_bev"]


def _check(boxes: Tensor, scores: Tensor, iou_threshold: float) -> None:
    dims: dict = {}
    check_shape(boxes, "boxes", ("N", 7), dims)
    check_shape(scores, "scores", ("N",), dims)
    check_floating(boxes, "boxes")
    check_floating(scores, "scores")
    if not 0.0 <= float(iou_threshold) <= 1.0:
        raise MSSFError(f"iou_threshold: expected a value in [0, 1], got {iou_threshold}")


def nms_bev(boxes: Tensor, scores: Tensor, iou_threshold: float, pre_max_size: int | None = None) -> Tensor:
    """Greedy rotated BEV NMS.

    Args:
        boxes: ``(N, 7)`` boxes ``(x, y, z, dx, dy, dz, yaw)``.
        scores: ``(N,)`` scores.
        iou_threshold: a box is suppressed when its BEV IoU with a kept, higher-ranked box is
            ``> iou_threshold``.
        pre_max_size: optionally keep only the ``pre_max_size`` best-scored boxes before NMS (bounds the
            ``O(N^2)`` IoU matrix).

    Returns:
        ``(K,)`` int64 indices into ``boxes`` of the kept boxes, in descending score order.
    """
    _check(boxes, scores, iou_threshold)
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    if pre_max_size is not None:
        order = order[:pre_max_size]
    overlaps = box_iou_bev(boxes[order], boxes[order]) > iou_threshold
    # A boolean matrix on the CPU makes the sequential part a cheap Python loop over kept boxes only.
    overlaps = overlaps.cpu()
    n = order.numel()
    suppressed = torch.zeros(n, dtype=torch.bool)
    keep = []
    for i in range(n):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= overlaps[i]
    keep_t = torch.tensor(keep, dtype=torch.long, device=boxes.device)
    return order[keep_t]


def nms_bev_reference(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """Slow reference of :func:`nms_bev`: one pairwise IoU call per (candidate, kept) pair."""
    _check(boxes, scores, iou_threshold)
    order = sorted(range(boxes.shape[0]), key=lambda i: (-float(scores[i]), i))
    keep: list = []
    for i in order:
        if all(float(box_iou_bev(boxes[i : i + 1], boxes[j : j + 1])[0, 0]) <= iou_threshold for j in keep):
            keep.append(i)
    return torch.tensor(keep, dtype=torch.long, device=boxes.device)


def batched_nms_bev(
    boxes: Tensor, scores: Tensor, labels: Tensor, iou_threshold: float, pre_max_size: int | None = None
) -> Tensor:
    """Per-class :func:`nms_bev`: boxes of different labels never suppress each other.

    Args:
        boxes: ``(N, 7)`` boxes.
        scores: ``(N,)`` scores.
        labels: ``(N,)`` integer class labels.
        iou_threshold: as in :func:`nms_bev`.
        pre_max_size: per-class cap before NMS.

    Returns:
        ``(K,)`` int64 indices of the kept boxes in descending score order (ties: lower index first).
    """
    _check(boxes, scores, iou_threshold)
    check_shape(labels, "labels", (boxes.shape[0],))
    keep = []
    for c in torch.unique(labels).tolist():
        members = torch.nonzero(labels == c).flatten()
        keep.append(members[nms_bev(boxes[members], scores[members], iou_threshold, pre_max_size)])
    if not keep:
        return torch.zeros(0, dtype=torch.long, device=boxes.device)
    keep_t = torch.sort(torch.cat(keep)).values  # index order first, so score ties keep it
    return keep_t[torch.sort(scores[keep_t], descending=True, stable=True).indices]
