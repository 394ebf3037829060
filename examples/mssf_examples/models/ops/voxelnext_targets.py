"""VoxelNeXt's own target assignment (OpenPCDet's ``VoxelNeXtHead.assign_target_of_single_head``, the MSSF
authors' ``VoxelNeXtHead.get_targets_single``), on the non-empty BEV voxels of one sample.

For each box (the first ``max_objs``, positive BEV size, centre cell inside the grid) with continuous grid
coordinates ``c = ((x - x_min) / cell_x, (y - y_min) / cell_y)``:

* its voxel is the one whose integer index ``(col, row)`` is nearest to ``c`` (squared distance, first on a
  tie): the box's positive, carrying the regression :func:`~mssf_examples.models.ops.boxes.encode_center`
  (offset from that integer index, centre ``z``, log sizes, ``(sin, cos)`` yaw; OpenPCDet writes ``(cos,
  sin)``);
* the heatmap of its class is max-combined with two untruncated Gaussians over all voxels,
  ``exp(-d / (2 sigma^2))`` with ``d`` the squared index distance to ``c`` (``'gt_center'``) and to the
  positive's index (``'nearst'``), ``sigma = (2 r + 1) / 6`` and ``r = max(min_radius, int(gaussian_radius))``
  (the CenterPoint radius of the box's size in cells).

This is not :func:`~mssf_examples.models.ops.targets.sparse_center_targets` (the examples' windowed,
integer-centred variant): the framework heads train as VoxelNeXt does. Where the two references differ, the
authors' rule is kept: a box whose truncated centre index lies outside the grid gets no target (OpenPCDet
clamps the centre into the grid; mmdet3d's ``ObjectRangeFilter`` removes such boxes anyway), and a sample
without voxels gets no target (both references fail on ``argmin`` of an empty tensor).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_shape

from .boxes import encode_center
from .targets import _check_gt, gaussian_radius

__all__ = ["VoxelNeXtTargets", "voxelnext_targets"]


@dataclass
class VoxelNeXtTargets:
    """Targets of one sample.

    Attributes:
        heatmap: ``(M, K)`` per voxel and class.
        voxel_index: ``(G',)`` int64 row (into the sample's voxels) of each kept box's positive.
        regression: ``(G', 8)`` targets at those rows.
        gt_index: ``(G',)`` int64 index of each kept box in the input.
    """

    heatmap: Tensor
    voxel_index: Tensor
    regression: Tensor
    gt_index: Tensor


def voxelnext_targets(gt_boxes: Tensor, gt_labels: Tensor, voxel_cells: Tensor, grid, num_classes: int,
                      min_overlap: float = 0.1, min_radius: int = 2, max_objs: int = 500) -> VoxelNeXtTargets:
    """VoxelNeXt targets of one sample (module docstring).

    Args:
        gt_boxes: ``(G, 7)`` boxes, centre ``z`` (``G`` may be 0).
        gt_labels: ``(G,)`` int64 labels in ``[0, K)``.
        voxel_cells: ``(M, 2)`` integer ``(col, row)`` of the sample's voxels on ``grid`` (``M`` may be 0).
        grid: the BEV grid at the head's stride (``x_min, y_min, cell_x, cell_y, nx, ny``).
        num_classes: ``K``.
        min_overlap, min_radius: the Gaussian radius settings (VoxelNeXt: 0.1, 2).
        max_objs: boxes beyond the first ``max_objs`` get no target (their ``NUM_MAX_OBJS`` / ``max_objs``).
    """
    _check_gt(gt_boxes, gt_labels, num_classes)
    check_shape(voxel_cells, "voxel_cells", ("M", 2))
    dtype, device = gt_boxes.dtype, gt_boxes.device
    m = voxel_cells.shape[0]
    heatmap = torch.zeros(m, num_classes, dtype=dtype, device=device)
    empty = torch.zeros(0, dtype=torch.long, device=device)
    boxes = gt_boxes[:max_objs]
    centre = torch.stack([(boxes[:, 0] - grid.x_min) / grid.cell_x, (boxes[:, 1] - grid.y_min) / grid.cell_y], 1)
    index = centre.trunc()  # their int cast: towards zero
    keep = (index[:, 0] >= 0) & (index[:, 0] < grid.nx) & (index[:, 1] >= 0) & (index[:, 1] < grid.ny)
    gt_index = torch.nonzero(keep).flatten()
    if m == 0 or gt_index.numel() == 0:
        return VoxelNeXtTargets(heatmap, empty, gt_boxes.new_zeros(0, 8), empty)
    radius = gaussian_radius(boxes[gt_index, 3] / grid.cell_x, boxes[gt_index, 4] / grid.cell_y, min_overlap)
    radius = torch.clamp(radius.to(torch.long), min=min_radius).to(dtype)
    sigma = (2 * radius + 1) / 6
    cells = voxel_cells.to(dtype)
    to_centre = ((cells[None] - centre[gt_index][:, None]) ** 2).sum(-1)  # (G', M)
    nearest = to_centre.argmin(dim=1)
    to_nearest = ((cells[None] - cells[nearest][:, None]) ** 2).sum(-1)
    weight = 1 / (2 * sigma * sigma)[:, None]
    gaussians = torch.maximum(torch.exp(-to_centre * weight), torch.exp(-to_nearest * weight))
    labels = gt_labels[gt_index].long()
    for g in range(gt_index.numel()):
        heatmap[:, labels[g]] = torch.maximum(heatmap[:, labels[g]], gaussians[g])
    regression = encode_center(boxes[gt_index], voxel_cells[nearest].long(), (grid.cell_x, grid.cell_y),
                               (grid.x_min, grid.y_min))
    return VoxelNeXtTargets(heatmap, nearest, regression, gt_index)
