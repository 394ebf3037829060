"""Pieces shared by the example detection heads: the BEV grid and the losses.

* :class:`BEVGrid`: the metric extent and cell layout of a dense BEV map ``(B, C, ny, nx)`` (row = y,
  column = x) or of the sparse BEV voxels at a given stride.
* :func:`sigmoid_focal_loss`: RetinaNet focal loss on logits (anchor head classification).
* :func:`gaussian_focal_loss`: the CenterNet variant against a Gaussian heatmap (centre heads):
  ``-(1 - p)^a log p`` at cells whose target is 1, ``-(1 - t)^b p^a log(1 - p)`` elsewhere.
* :func:`smooth_l1`: Huber-style regression loss with OpenPCDet's ``beta = 1/9``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mssf_blocks.errors import MSSFError

from ..ops.nms import batched_nms_bev, nms_bev

__all__ = [
    "BEVGrid",
    "sigmoid_focal_loss",
    "gaussian_focal_loss",
    "smooth_l1",
    "check_gt_lists",
    "select_detections",
    "check_decode_args",
    "check_center_range",
    "centers_in_range",
]


@dataclass(frozen=True)
class BEVGrid:
    """A bird's-eye-view grid of ``ny x nx`` cells over ``[x_min, x_max) x [y_min, y_max)`` metres.

    Cell ``(row, col)`` covers ``[x_min + col * cell_x, x_min + (col + 1) * cell_x)`` in x and the
    analogous interval in y; its centre is at ``+0.5`` cells. For a voxel detector at BEV stride ``s`` and
    voxel size ``v``: ``nx = W / s`` and ``cell_x = v_x * s``.
    """

    x_min: float
    y_min: float
    x_max: float
    y_max: float
    ny: int
    nx: int

    def __post_init__(self) -> None:
        for name in ("x_min", "y_min", "x_max", "y_max"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise MSSFError(f"BEVGrid.{name}: expected a finite number, got {value!r}")
        for name in ("ny", "nx"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
                raise MSSFError(f"BEVGrid.{name}: expected a positive int, got {value!r}")
        if not (self.x_max > self.x_min and self.y_max > self.y_min):
            raise MSSFError(
                f"BEVGrid: expected x_max > x_min and y_max > y_min, got x [{self.x_min}, {self.x_max}], "
                f"y [{self.y_min}, {self.y_max}]"
            )

    @property
    def cell_x(self) -> float:
        """Cell size along x in metres."""
        return (self.x_max - self.x_min) / self.nx

    @property
    def cell_y(self) -> float:
        """Cell size along y in metres."""
        return (self.y_max - self.y_min) / self.ny

    def cell_centers(self, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
        """``(ny, nx, 2)`` metric ``(x, y)`` of every cell centre."""
        xs = (torch.arange(self.nx, dtype=torch.float64) + 0.5) * self.cell_x + self.x_min
        ys = (torch.arange(self.ny, dtype=torch.float64) + 0.5) * self.cell_y + self.y_min
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")
        return torch.stack([xx, yy], dim=-1).to(dtype=dtype, device=device)


def sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """Element-wise RetinaNet focal loss (no reduction) of ``logits`` against 0/1 ``targets``."""
    p = torch.sigmoid(logits)
    ce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = p * targets + (1 - p) * (1 - targets)
    alpha_t = alpha * targets + (1 - alpha) * (1 - targets)
    return alpha_t * (1 - p_t) ** gamma * ce


def gaussian_focal_loss(logits: Tensor, heatmap: Tensor, alpha: float = 2.0, beta: float = 4.0) -> Tensor:
    """CenterNet focal loss summed over all entries and divided by ``max(1, #entries equal to 1)``.

    ``p = sigmoid(logits)`` is clamped to ``[1e-4, 1 - 1e-4]`` as CenterPoint does.
    """
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    positive = heatmap.eq(1).to(p.dtype)
    pos_loss = -torch.log(p) * (1 - p) ** alpha * positive
    neg_loss = -torch.log(1 - p) * p**alpha * (1 - heatmap) ** beta * (1 - positive)
    return (pos_loss.sum() + neg_loss.sum()) / positive.sum().clamp(min=1)


def smooth_l1(diff: Tensor, beta: float = 1.0 / 9.0) -> Tensor:
    """Element-wise smooth-L1 of a difference ``diff``."""
    n = diff.abs()
    return torch.where(n < beta, 0.5 * n**2 / beta, n - 0.5 * beta)


def check_gt_lists(gt_boxes, gt_labels, batch_size: int, num_classes: int) -> None:
    """Validate the per-sample ground-truth lists every head's ``loss`` takes."""
    if len(gt_boxes) != batch_size or len(gt_labels) != batch_size:
        raise MSSFError(
            f"gt_boxes/gt_labels: expected {batch_size} entries (one per sample), "
            f"got {len(gt_boxes)} and {len(gt_labels)}"
        )
    for b, (boxes, labels) in enumerate(zip(gt_boxes, gt_labels)):
        if not isinstance(boxes, Tensor) or boxes.dim() != 2 or boxes.shape[1] != 7:
            raise MSSFError(f"gt_boxes[{b}]: expected a (G, 7) tensor, got {getattr(boxes, 'shape', boxes)!r}")
        if not isinstance(labels, Tensor) or labels.shape != (boxes.shape[0],):
            raise MSSFError(
                f"gt_labels[{b}]: expected shape ({boxes.shape[0]},), got {getattr(labels, 'shape', labels)!r}"
            )
        if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= num_classes):
            raise MSSFError(
                f"gt_labels[{b}]: expected values in [0, {num_classes}), got [{int(labels.min())}, {int(labels.max())}]"
            )


def select_detections(
    boxes: Tensor,
    scores: Tensor,
    labels: Tensor,
    score_threshold: float,
    nms_iou: float | None,
    max_detections: int,
    nms_pre: int | None = None,
    class_agnostic_nms: bool = False,
    center_range=None,
) -> dict:
    """Score threshold (``> score_threshold``), per-class rotated NMS and the final cap, for one sample.

    Args:
        boxes: ``(N, 7)``; scores: ``(N,)``; labels: ``(N,)`` int64.
        score_threshold: keep scores strictly above it.
        nms_iou: per-class BEV NMS threshold, or ``None`` for no NMS.
        max_detections: keep at most this many (best first).
        nms_pre: keep at most this many best boxes before NMS.
        class_agnostic_nms: one NMS over all labels (a box suppresses overlapping boxes of any class), as
            the MSSF authors' VoxelNeXt head; default per class.
        center_range: ``(x0, y0, z0, x1, y1, z1)``: before NMS, drop boxes whose centre is outside it
            (bounds inclusive), as the authors' VoxelNeXt box coder; default no filter.

    Returns:
        ``dict(boxes (K, 7), scores (K,), labels (K,))`` sorted by descending score.
    """
    keep = torch.nonzero(scores > score_threshold).flatten()
    keep = keep[torch.sort(scores[keep], descending=True, stable=True).indices]
    if nms_pre is not None:
        keep = keep[:nms_pre]
    if center_range is not None:
        keep = keep[centers_in_range(boxes[keep], center_range)]
    if nms_iou is not None and keep.numel():
        if class_agnostic_nms:
            keep = keep[nms_bev(boxes[keep].detach(), scores[keep].detach(), nms_iou)]
        else:
            keep = keep[batched_nms_bev(boxes[keep].detach(), scores[keep].detach(), labels[keep], nms_iou)]
    keep = keep[:max_detections]
    return {"boxes": boxes[keep], "scores": scores[keep], "labels": labels[keep]}


def check_decode_args(score_threshold: float, nms_iou: float | None, max_detections: int) -> None:
    """Validate the common ``decode`` arguments."""
    if not math.isfinite(float(score_threshold)):
        raise MSSFError(f"score_threshold: expected a finite number, got {score_threshold}")
    if nms_iou is not None and not 0.0 <= float(nms_iou) <= 1.0:
        raise MSSFError(f"nms_iou: expected None or a value in [0, 1], got {nms_iou}")
    if isinstance(max_detections, bool) or not isinstance(max_detections, int) or max_detections < 0:
        raise MSSFError(f"max_detections: expected a non-negative int, got {max_detections!r}")


def check_center_range(center_range) -> tuple:
    """``center_range`` as six floats ``(x0, y0, z0, x1, y1, z1)`` with ``x0 <= x1`` etc., or a clear error."""
    try:
        values = tuple(float(v) for v in center_range)
    except (TypeError, ValueError):
        raise MSSFError(f"center_range: expected six numbers (x0, y0, z0, x1, y1, z1), got {center_range!r}") from None
    if len(values) != 6 or not all(math.isfinite(v) for v in values) or any(
            values[i] > values[i + 3] for i in range(3)):
        raise MSSFError(f"center_range: expected six finite numbers (x0, y0, z0, x1, y1, z1) with lower <= upper, "
                        f"got {center_range!r}")
    return values


def centers_in_range(boxes: Tensor, center_range) -> Tensor:
    """``(N,)`` bool: the centre ``boxes[:, :3]`` lies inside ``center_range`` (bounds inclusive)."""
    r = torch.tensor(check_center_range(center_range), dtype=boxes.dtype, device=boxes.device)
    return ((boxes[:, :3] >= r[:3]) & (boxes[:, :3] <= r[3:])).all(dim=1)
