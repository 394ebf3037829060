"""Training-target assignment for the example detection heads.

* **Anchors** (SECOND / PointPillars, as OpenPCDet's ``AxisAlignedTargetAssigner``): anchors of class
  ``k`` are matched only to ground truth of class ``k`` by a BEV IoU; an anchor is positive when its
  best IoU is ``>= matched_threshold[k]``, background when it is ``< unmatched_threshold[k]``, ignored
  in between; additionally every ground-truth box forces the anchor(s) with its highest (non-zero) IoU to
  be positive. The IoU is OpenPCDet's **"nearest BEV" IoU**: each rotated box is replaced by the
  axis-aligned rectangle of its footprint after rounding its yaw to the nearest multiple of ``pi/2``
  (``dx, dy`` swapped when ``|yaw mod pi| > pi/4``), and the 2-D IoU of those rectangles is used. It is
  cheap, exact for the axis-aligned anchors of a ``(0, pi/2)`` rotation set, and is what the reference
  implementations train with; the rotated IoU in :mod:`mssf_examples.models.ops.iou` is for NMS and evaluation.
* **Centre heatmaps** (CenterPoint): each box draws a Gaussian of radius ``max(min_radius,
  int(gaussian_radius(dx_cells, dy_cells, min_overlap)))`` (the CenterNet / CenterPoint radius formula,
  in feature-map cells) centred on the cell that contains its centre, ``sigma = (2 r + 1) / 6``, over the
  ``(2 r + 1)^2`` window, combined by element-wise max. Unlike CenterNet we do not zero values below
  ``eps * max`` (they are ``< 1e-6`` of the peak and irrelevant to the loss).
* **Sparse centre targets** (VoxelNeXt): the voxel whose cell centre is nearest to a box centre is the
  box's positive and carries its regression target, wherever the box centre falls. The heatmap at the
  voxels is the max of the dense heatmap read at the voxels and the same Gaussian (same radius)
  centred on the assigned voxel's cell, so the positive has value exactly 1. VoxelNeXt does the same
  with untruncated Gaussians of the squared distance to the float centre; ours are windowed and
  integer-centred so that a voxel at the centre's cell gets exactly the dense head's target.

A grid is any object with ``x_min, y_min, cell_x, cell_y, ny, nx`` (e.g.
:class:`mssf_examples.models.heads.common.BEVGrid`); cell ``(col, row)`` covers
``[x_min + col * cell_x, x_min + (col + 1) * cell_x) x [y_min + row * cell_y, ...)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.errors import MSSFError

from .boxes import encode_center, limit_period

__all__ = [
    "nearest_bev_boxes",
    "axis_aligned_iou",
    "nearest_bev_iou",
    "AnchorTargets",
    "assign_anchor_targets",
    "gaussian_radius",
    "draw_gaussian",
    "CenterTargets",
    "center_targets",
    "SparseCenterTargets",
    "sparse_center_targets",
]


def nearest_bev_boxes(boxes: Tensor) -> Tensor:
    """Axis-aligned ``(x1, y1, x2, y2)`` footprint of ``(N, 7)`` boxes with yaw rounded to ``k * pi/2``."""
    yaw = torch.abs(limit_period(boxes[:, 6], 0.5, math.pi))
    swap = yaw > math.pi / 4
    half_x = torch.where(swap, boxes[:, 4], boxes[:, 3]) / 2
    half_y = torch.where(swap, boxes[:, 3], boxes[:, 4]) / 2
    return torch.stack([boxes[:, 0] - half_x, boxes[:, 1] - half_y, boxes[:, 0] + half_x, boxes[:, 1] + half_y], -1)


def axis_aligned_iou(a: Tensor, b: Tensor) -> Tensor:
    """IoU of ``(N, 4)`` and ``(M, 4)`` ``(x1, y1, x2, y2)`` rectangles -> ``(N, M)`` (0 when both empty)."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area_a = (a[:, 2:] - a[:, :2]).prod(-1)
    area_b = (b[:, 2:] - b[:, :2]).prod(-1)
    union = area_a[:, None] + area_b[None, :] - inter
    return torch.where(union > 0, inter / union.clamp(min=torch.finfo(a.dtype).tiny), torch.zeros_like(inter))


def nearest_bev_iou(a: Tensor, b: Tensor) -> Tensor:
    """OpenPCDet's anchor-matching IoU of ``(N, 7)`` and ``(M, 7)`` boxes -> ``(N, M)`` (see module doc)."""
    return axis_aligned_iou(nearest_bev_boxes(a), nearest_bev_boxes(b))


@dataclass
class AnchorTargets:
    """Per-anchor assignment.

    Attributes:
        labels: ``(A,)`` int64: ``-1`` ignored, ``0`` background, ``k + 1`` positive of class ``k``.
        matched_gt: ``(A,)`` int64 index into the sample's ground truth for positives, ``-1`` elsewhere.
    """

    labels: Tensor
    matched_gt: Tensor


def _per_class(values: float | Sequence[float], num_classes: int, name: str) -> list:
    if isinstance(values, (int, float)):
        values = [float(values)] * num_classes
    values = [float(v) for v in values]
    if len(values) != num_classes:
        raise MSSFError(f"{name}: expected {num_classes} values (one per class), got {len(values)}")
    return values


def assign_anchor_targets(
    anchors: Tensor,
    anchor_classes: Tensor,
    gt_boxes: Tensor,
    gt_labels: Tensor,
    matched_thresholds: float | Sequence[float],
    unmatched_thresholds: float | Sequence[float],
    num_classes: int,
) -> AnchorTargets:
    """Assign one sample's anchors to its ground truth (see the module docstring for the rule).

    Args:
        anchors: ``(A, 7)`` anchors.
        anchor_classes: ``(A,)`` int64 class each anchor is for.
        gt_boxes: ``(G, 7)`` ground-truth boxes (``G`` may be 0).
        gt_labels: ``(G,)`` int64 labels in ``[0, num_classes)``.
        matched_thresholds: one IoU per class (or one for all) for positives.
        unmatched_thresholds: one IoU per class (or one for all) below which anchors are background.
        num_classes: number of classes ``K``.

    Returns:
        :class:`AnchorTargets`.
    """
    dims: dict = {}
    check_shape(anchors, "anchors", ("A", 7), dims)
    check_shape(anchor_classes, "anchor_classes", ("A",), dims)
    _check_gt(gt_boxes, gt_labels, num_classes)
    matched = _per_class(matched_thresholds, num_classes, "matched_thresholds")
    unmatched = _per_class(unmatched_thresholds, num_classes, "unmatched_thresholds")
    device = anchors.device
    labels = torch.full((anchors.shape[0],), -1, dtype=torch.long, device=device)
    matched_gt = torch.full_like(labels, -1)
    for k in range(num_classes):
        anchor_ids = torch.nonzero(anchor_classes == k).flatten()
        gt_ids = torch.nonzero(gt_labels == k).flatten()
        if anchor_ids.numel() == 0:
            continue
        if gt_ids.numel() == 0:
            labels[anchor_ids] = 0
            continue
        iou = nearest_bev_iou(anchors[anchor_ids], gt_boxes[gt_ids].to(anchors.dtype))  # (A_k, G_k)
        best_iou, best_gt = iou.max(dim=1)
        gt_best = iou.max(dim=0).values
        # A box that overlaps no anchor at all forces nothing (OpenPCDet sets its max to -1).
        gt_best = torch.where(gt_best > 0, gt_best, torch.full_like(gt_best, -1.0))
        forced = (iou == gt_best[None, :]).any(dim=1)
        local = torch.full((anchor_ids.numel(),), -1, dtype=torch.long, device=device)
        local_gt = torch.full_like(local, -1)
        positive = (best_iou >= matched[k]) | forced
        local[best_iou < unmatched[k]] = 0
        local[positive] = k + 1
        local_gt[positive] = gt_ids[best_gt[positive]]
        labels[anchor_ids] = local
        matched_gt[anchor_ids] = local_gt
    return AnchorTargets(labels=labels, matched_gt=matched_gt)


def gaussian_radius(dx: Tensor, dy: Tensor, min_overlap: float = 0.5) -> Tensor:
    """CenterNet / CenterPoint Gaussian radius for a box of BEV size ``dx x dy`` (in cells).

    The smallest of the three radii at which a corner-shifted box keeps IoU ``min_overlap`` with the
    true one, written exactly as CenterPoint does (including its ``(b + sqrt(b^2 - 4ac)) / 2`` form).
    """
    a1 = 1.0
    b1 = dx + dy
    c1 = dx * dy * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + torch.sqrt(b1**2 - 4 * a1 * c1)) / 2
    a2 = 4.0
    b2 = 2 * (dx + dy)
    c2 = (1 - min_overlap) * dx * dy
    r2 = (b2 + torch.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (dx + dy)
    c3 = (min_overlap - 1) * dx * dy
    r3 = (b3 + torch.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return torch.minimum(torch.minimum(r1, r2), r3)


def draw_gaussian(heatmap: Tensor, col: int, row: int, radius: int) -> Tensor:
    """Max-combine a Gaussian of integer ``radius`` centred on cell ``(col, row)`` into ``heatmap`` (ny, nx).

    Modifies ``heatmap`` in place (clipped at the map border) and returns it.
    """
    ny, nx = heatmap.shape
    sigma = (2 * radius + 1) / 6.0
    left, right = min(col, radius), min(nx - col, radius + 1)
    top, bottom = min(row, radius), min(ny - row, radius + 1)
    if left + right <= 0 or top + bottom <= 0:
        return heatmap
    ys = torch.arange(-top, bottom, dtype=heatmap.dtype, device=heatmap.device)
    xs = torch.arange(-left, right, dtype=heatmap.dtype, device=heatmap.device)
    gaussian = torch.exp(-(ys[:, None] ** 2 + xs[None, :] ** 2) / (2 * sigma * sigma))
    window = heatmap[row - top : row + bottom, col - left : col + right]
    torch.maximum(window, gaussian, out=window)
    return heatmap


def _box_cells(gt_boxes: Tensor, grid) -> tuple:
    u = (gt_boxes[:, 0] - grid.x_min) / grid.cell_x
    v = (gt_boxes[:, 1] - grid.y_min) / grid.cell_y
    inside = (u >= 0) & (u < grid.nx) & (v >= 0) & (v < grid.ny)
    return u, v, inside


def _radii(gt_boxes: Tensor, grid, min_overlap: float, min_radius: int) -> Tensor:
    r = gaussian_radius(gt_boxes[:, 3] / grid.cell_x, gt_boxes[:, 4] / grid.cell_y, min_overlap)
    return torch.clamp(r.to(torch.long), min=min_radius)  # int() truncation, as CenterPoint


def _check_gt(gt_boxes: Tensor, gt_labels: Tensor, num_classes: int) -> None:
    dims: dict = {}
    check_shape(gt_boxes, "gt_boxes", ("G", 7), dims)
    check_shape(gt_labels, "gt_labels", ("G",), dims)
    check_floating(gt_boxes, "gt_boxes")
    if gt_labels.numel() and (int(gt_labels.min()) < 0 or int(gt_labels.max()) >= num_classes):
        raise MSSFError(
            f"gt_labels: expected values in [0, {num_classes}), got values in "
            f"[{int(gt_labels.min())}, {int(gt_labels.max())}]"
        )
    if gt_boxes.numel() and bool((gt_boxes[:, 3:6] <= 0).any()):
        raise MSSFError("gt_boxes: expected positive sizes (columns 3..5), got a size <= 0")


@dataclass
class CenterTargets:
    """Dense centre-head targets of one sample (only boxes whose centre lies inside the grid).

    Attributes:
        heatmap: ``(K, ny, nx)`` Gaussian heatmap.
        cell_index: ``(G', 2)`` int64 ``(col, row)`` of each kept box's centre cell.
        regression: ``(G', 8)`` :func:`~mssf_examples.models.ops.boxes.encode_center` targets.
        labels: ``(G',)`` class of each kept box.
        gt_index: ``(G',)`` index of each kept box in the input.
        radius: ``(G',)`` int64 Gaussian radius in cells.
    """

    heatmap: Tensor
    cell_index: Tensor
    regression: Tensor
    labels: Tensor
    gt_index: Tensor
    radius: Tensor


def center_targets(
    gt_boxes: Tensor, gt_labels: Tensor, grid, num_classes: int, min_overlap: float = 0.1, min_radius: int = 2
) -> CenterTargets:
    """CenterPoint targets of one sample on ``grid`` (boxes with centres outside the grid get none).

    Args:
        gt_boxes: ``(G, 7)`` boxes (``G`` may be 0).
        gt_labels: ``(G,)`` int64 labels in ``[0, K)``.
        grid: the BEV grid of the feature map.
        num_classes: ``K``.
        min_overlap: Gaussian-radius IoU (CenterPoint uses 0.1).
        min_radius: smallest radius in cells (CenterPoint: 2).
    """
    _check_gt(gt_boxes, gt_labels, num_classes)
    heatmap = torch.zeros(num_classes, grid.ny, grid.nx, dtype=gt_boxes.dtype, device=gt_boxes.device)
    u, v, inside = _box_cells(gt_boxes, grid)
    keep = torch.nonzero(inside).flatten()
    boxes = gt_boxes[keep]
    cells = torch.stack([u[keep].floor(), v[keep].floor()], -1).to(torch.long)
    radius = _radii(boxes, grid, min_overlap, min_radius)
    for g in range(keep.numel()):
        draw_gaussian(heatmap[int(gt_labels[keep[g]])], int(cells[g, 0]), int(cells[g, 1]), int(radius[g]))
    regression = encode_center(boxes, cells, (grid.cell_x, grid.cell_y), (grid.x_min, grid.y_min))
    return CenterTargets(heatmap, cells, regression, gt_labels[keep], keep, radius)


@dataclass
class SparseCenterTargets:
    """Sparse (per-voxel) centre-head targets of one sample.

    Attributes:
        heatmap: ``(M, K)`` the dense Gaussian heatmap read at each voxel, max-combined with a Gaussian
            around each box's voxel (which therefore holds 1).
        voxel_index: ``(G',)`` int64 row (into the sample's voxels) of the voxel assigned to each box.
        regression: ``(G', 8)`` :func:`~mssf_examples.models.ops.boxes.encode_center` targets at that voxel.
        labels: ``(G',)`` classes; gt_index: ``(G',)`` indices into the input boxes.
    """

    heatmap: Tensor
    voxel_index: Tensor
    regression: Tensor
    labels: Tensor
    gt_index: Tensor


def sparse_center_targets(
    gt_boxes: Tensor,
    gt_labels: Tensor,
    voxel_cells: Tensor,
    grid,
    num_classes: int,
    min_overlap: float = 0.1,
    min_radius: int = 2,
) -> SparseCenterTargets:
    """VoxelNeXt targets of one sample on its non-empty BEV voxels.

    Args:
        gt_boxes: ``(G, 7)`` boxes (``G`` may be 0).
        gt_labels: ``(G,)`` int64 labels.
        voxel_cells: ``(M, 2)`` int64 ``(col, row)`` of the sample's voxels on ``grid`` (``M`` may be 0;
            then no box is assigned).
        grid: the BEV grid at the head's stride.
        num_classes: ``K``.
        min_overlap, min_radius: as in :func:`center_targets`.
    """
    _check_gt(gt_boxes, gt_labels, num_classes)
    check_shape(voxel_cells, "voxel_cells", ("M", 2))
    dense = center_targets(gt_boxes, gt_labels, grid, num_classes, min_overlap, min_radius)
    cols, rows = voxel_cells[:, 0].long(), voxel_cells[:, 1].long()
    heatmap = dense.heatmap[:, rows, cols].T.contiguous()  # (M, K)
    empty = torch.zeros(0, dtype=torch.long, device=gt_boxes.device)
    if voxel_cells.shape[0] == 0 or dense.gt_index.numel() == 0:
        return SparseCenterTargets(heatmap, empty, gt_boxes.new_zeros(0, 8), empty, empty)
    u, v, _ = _box_cells(gt_boxes[dense.gt_index], grid)
    centres = voxel_cells.to(gt_boxes.dtype) + 0.5
    dist2 = (centres[None, :, 0] - u[:, None]) ** 2 + (centres[None, :, 1] - v[:, None]) ** 2  # (G', M)
    nearest = dist2.argmin(dim=1)
    # As VoxelNeXt, a second Gaussian around the assigned voxel, so that when the centre's own cell is
    # empty the voxels next to the positive are not penalised as full negatives.
    offsets = (voxel_cells[None, :, :] - voxel_cells[nearest][:, None, :]).to(gt_boxes.dtype)  # (G', M, 2)
    radius = dense.radius.to(gt_boxes.dtype)[:, None]
    sigma = (2 * radius + 1) / 6
    around = torch.exp(-(offsets**2).sum(-1) / (2 * sigma * sigma))
    around = torch.where((offsets.abs() <= radius[..., None]).all(-1), around, torch.zeros_like(around))
    for g in range(nearest.numel()):
        k = int(dense.labels[g])
        heatmap[:, k] = torch.maximum(heatmap[:, k], around[g])
    regression = encode_center(
        gt_boxes[dense.gt_index], voxel_cells[nearest].long(), (grid.cell_x, grid.cell_y), (grid.x_min, grid.y_min)
    )
    return SparseCenterTargets(heatmap, nearest, regression, dense.labels, dense.gt_index)
