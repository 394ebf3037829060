"""Anchor-based dense BEV head (SECOND / PointPillars, as OpenPCDet's ``AnchorHeadSingle``).

At every BEV cell centre there is one anchor per (class, rotation); three 1x1 convolutions predict per
anchor: ``K`` class logits (sigmoid focal loss), the residual box code of
:func:`mssf_examples.models.ops.boxes.encode_residual` (smooth-L1; with the raw-angle code the yaw term uses the
"sin-difference" trick ``sin(p - t) = sin p cos t - cos p sin t``, so yaw and yaw + pi cost the same), and a
direction bin (cross-entropy) that resolves the remaining pi ambiguity at decode time.

Anchor sizes are ``(dx, dy, dz)`` = (length along the heading, width, height). The paper's settings:

* VoD (stated as l, w, h): car ``(3.9, 1.6, 1.56)``, pedestrian ``(0.8, 0.6, 1.73)``,
  cyclist ``(1.76, 0.6, 1.73)``.
* TJ4DRadSet is printed as car ``(1.84, 4.56, 1.70)``, pedestrian ``(0.6, 0.8, 1.69)``, cyclist
  ``(0.78, 1.77, 1.60)``, truck ``(2.66, 10.76, 3.47)``: the first value is always the smaller one, i.e.
  the old mmdetection3d ``(w, l, h)`` order, so we use ``(dx, dy, dz)`` = ``(4.56, 1.84, 1.70)``,
  ``(0.8, 0.6, 1.69)``, ``(1.77, 0.78, 1.60)``, ``(10.76, 2.66, 3.47)``. With the default rotations
  ``(0, pi/2)`` both orientations exist anyway, so only the direction-bin convention depends on it.
  :data:`VOD_ANCHOR_SIZES` and :data:`TJ4D_ANCHOR_SIZES` hold these.
"""

from __future__ import annotations

import math
from typing import Dict, List, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.errors import MSSFError

from ..ops.boxes import decode_residual, encode_residual, limit_period, residual_code_size
from ..ops.targets import assign_anchor_targets
from .common import (
    BEVGrid,
    check_decode_args,
    check_gt_lists,
    select_detections,
    sigmoid_focal_loss,
    smooth_l1,
)

__all__ = ["AnchorHead", "make_anchors", "VOD_ANCHOR_SIZES", "TJ4D_ANCHOR_SIZES"]

#: ``(dx, dy, dz)`` anchors for VoD (car, pedestrian, cyclist), as printed in the paper.
VOD_ANCHOR_SIZES = ((3.9, 1.6, 1.56), (0.8, 0.6, 1.73), (1.76, 0.6, 1.73))
#: ``(dx, dy, dz)`` anchors for TJ4DRadSet (car, pedestrian, cyclist, truck): the paper's ``(w, l, h)``
#: values reordered (see the module docstring).
TJ4D_ANCHOR_SIZES = ((4.56, 1.84, 1.70), (0.8, 0.6, 1.69), (1.77, 0.78, 1.60), (10.76, 2.66, 3.47))


def make_anchors(
    grid: BEVGrid,
    anchor_sizes: Sequence[Sequence[float]],
    anchor_z_centers: Sequence[float],
    rotations: Sequence[float],
    dtype: torch.dtype = torch.float32,
    device=None,
) -> tuple:
    """Anchors at every cell centre of ``grid``.

    Returns:
        ``anchors (ny * nx * K * R, 7)`` ordered ``(row, col, class, rotation)`` and
        ``anchor_classes (ny * nx * K * R,)`` int64.
    """
    centres = grid.cell_centers(torch.float64)  # (ny, nx, 2)
    num_classes, num_rot = len(anchor_sizes), len(rotations)
    per_loc = torch.tensor(
        [
            [0.0, 0.0, float(anchor_z_centers[k]), *map(float, anchor_sizes[k]), float(r)]
            for k in range(num_classes)
            for r in rotations
        ],
        dtype=torch.float64,
    )  # (K*R, 7)
    anchors = per_loc.expand(grid.ny, grid.nx, -1, -1).clone()
    anchors[..., :2] += centres[:, :, None, :]
    classes = torch.arange(num_classes).repeat_interleave(num_rot).expand(grid.ny, grid.nx, -1)
    return anchors.reshape(-1, 7).to(dtype=dtype, device=device), classes.reshape(-1).to(device)


class AnchorHead(nn.Module):
    """SECOND / PointPillars anchor head on a dense BEV map.

    Args:
        in_channels: channels ``C`` of the BEV map.
        grid: the map's :class:`BEVGrid`.
        anchor_sizes: one ``(dx, dy, dz)`` per class (``K`` classes).
        anchor_z_centers: one anchor centre ``z`` per class.
        rotations: anchor yaws, the same for every class (``R`` of them).
        matched_thresholds: nearest-BEV IoU for positives, per class or one for all (0.6 for cars,
            0.5 for pedestrians/cyclists in the usual configs).
        unmatched_thresholds: IoU below which anchors are background, per class or one for all.
        encode_angle_by_sincos: use the 8-value ``(cos, sin)`` yaw residual instead of the raw one.
        use_direction_classifier: predict the direction bin (needed with the raw/sin-difference yaw).
        dir_offset: OpenPCDet's ``DIR_OFFSET`` (pi/4): bin boundaries at ``dir_offset + k * 2 pi / bins``.
        dir_limit_offset: OpenPCDet's ``DIR_LIMIT_OFFSET``.
        num_dir_bins: number of direction bins.
        cls_weight, reg_weight, dir_weight: loss weights (OpenPCDet: 1, 2, 0.2).
        code_weights: per-code-entry regression weights (default all ones).
        nms_pre: best boxes per sample kept before NMS at decode.
        device, dtype: for the parameters.

    Shape:
        ``forward(bev (B, C, ny, nx)) -> dict(cls (B, A, K), box (B, A, code), dir (B, A, bins))`` with
        ``A = ny * nx * K * R`` in the order of :attr:`anchors`.
    """

    def __init__(
        self,
        in_channels: int,
        grid: BEVGrid,
        anchor_sizes: Sequence[Sequence[float]],
        anchor_z_centers: Sequence[float],
        rotations: Sequence[float] = (0.0, math.pi / 2),
        matched_thresholds: float | Sequence[float] = 0.6,
        unmatched_thresholds: float | Sequence[float] = 0.45,
        encode_angle_by_sincos: bool = False,
        use_direction_classifier: bool = True,
        dir_offset: float = math.pi / 4,
        dir_limit_offset: float = 0.0,
        num_dir_bins: int = 2,
        cls_weight: float = 1.0,
        reg_weight: float = 2.0,
        dir_weight: float = 0.2,
        code_weights: Sequence[float] | None = None,
        nms_pre: int = 1000,
        device=None,
        dtype=None,
    ) -> None:
        super().__init__()
        if not isinstance(grid, BEVGrid):
            raise MSSFError(f"grid: expected a BEVGrid, got {type(grid).__name__}")
        check_positive_int(in_channels, "in_channels")
        if len(anchor_sizes) == 0 or any(len(s) != 3 or min(map(float, s)) <= 0 for s in anchor_sizes):
            raise MSSFError(f"anchor_sizes: expected one positive (dx, dy, dz) per class, got {anchor_sizes!r}")
        if len(anchor_z_centers) != len(anchor_sizes):
            raise MSSFError(
                f"anchor_z_centers: expected {len(anchor_sizes)} values (one per class), got {len(anchor_z_centers)}"
            )
        if len(rotations) == 0:
            raise MSSFError("rotations: expected at least one anchor yaw, got none")
        if num_dir_bins < 1:
            raise MSSFError(f"num_dir_bins: expected a positive int, got {num_dir_bins}")
        self.grid = grid
        self.in_channels = in_channels
        self.num_classes = len(anchor_sizes)
        self.num_anchors_per_location = self.num_classes * len(rotations)
        self.matched_thresholds = matched_thresholds
        self.unmatched_thresholds = unmatched_thresholds
        self.encode_angle_by_sincos = encode_angle_by_sincos
        self.code_size = residual_code_size(encode_angle_by_sincos)
        self.use_direction_classifier = use_direction_classifier
        self.dir_offset, self.dir_limit_offset, self.num_dir_bins = dir_offset, dir_limit_offset, num_dir_bins
        self.cls_weight, self.reg_weight, self.dir_weight = cls_weight, reg_weight, dir_weight
        self.nms_pre = nms_pre
        code_weights = [1.0] * self.code_size if code_weights is None else list(map(float, code_weights))
        if len(code_weights) != self.code_size:
            raise MSSFError(f"code_weights: expected {self.code_size} values, got {len(code_weights)}")
        factory = {"device": device, "dtype": dtype}
        anchors, classes = make_anchors(grid, anchor_sizes, anchor_z_centers, rotations, dtype or torch.float32, device)
        self.register_buffer("anchors", anchors, persistent=False)
        self.register_buffer("anchor_classes", classes, persistent=False)
        self.register_buffer("code_weights", torch.tensor(code_weights, **factory), persistent=False)
        na = self.num_anchors_per_location
        self.conv_cls = nn.Conv2d(in_channels, na * self.num_classes, 1, **factory)
        self.conv_box = nn.Conv2d(in_channels, na * self.code_size, 1, **factory)
        self.conv_dir = nn.Conv2d(in_channels, na * num_dir_bins, 1, **factory) if use_direction_classifier else None
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Focal-loss prior (p = 0.01) for the class bias, small box weights (as OpenPCDet)."""
        nn.init.constant_(self.conv_cls.bias, -math.log((1 - 0.01) / 0.01))
        nn.init.normal_(self.conv_box.weight, mean=0.0, std=0.001)
        nn.init.zeros_(self.conv_box.bias)

    def extra_repr(self) -> str:
        return (
            f"in_channels={self.in_channels}, num_classes={self.num_classes}, "
            f"anchors_per_location={self.num_anchors_per_location}, grid={self.grid}"
        )

    def _flatten(self, x: Tensor, per_anchor: int) -> Tensor:
        b = x.shape[0]
        return x.permute(0, 2, 3, 1).reshape(b, -1, per_anchor)

    def forward(self, bev: Tensor) -> Dict[str, Tensor]:
        """Predict per-anchor logits, box codes and direction logits from ``bev (B, C, ny, nx)``."""
        check_shape(bev, "bev", ("B", self.in_channels, self.grid.ny, self.grid.nx))
        check_floating(bev, "bev")
        preds = {
            "cls": self._flatten(self.conv_cls(bev), self.num_classes),
            "box": self._flatten(self.conv_box(bev), self.code_size),
        }
        if self.conv_dir is not None:
            preds["dir"] = self._flatten(self.conv_dir(bev), self.num_dir_bins)
        return preds

    def loss(self, preds: Dict[str, Tensor], gt_boxes: List[Tensor], gt_labels: List[Tensor]) -> Dict[str, Tensor]:
        """Focal classification, smooth-L1 box and direction losses, each averaged over the batch.

        Per sample, every loss is normalised by its number of positive anchors (at least 1).

        Returns:
            ``dict(cls, reg[, dir])`` of scalar tensors (already multiplied by the loss weights).
        """
        cls_preds, box_preds = preds["cls"], preds["box"]
        batch_size = cls_preds.shape[0]
        check_gt_lists(gt_boxes, gt_labels, batch_size, self.num_classes)
        zero = cls_preds.sum() * 0.0
        cls_loss, reg_loss, dir_loss = zero, zero, zero
        for b in range(batch_size):
            boxes = gt_boxes[b].to(self.anchors)
            t = assign_anchor_targets(
                self.anchors, self.anchor_classes, boxes, gt_labels[b].to(self.anchors.device).long(),
                self.matched_thresholds, self.unmatched_thresholds, self.num_classes,
            )
            positive = t.labels > 0
            normaliser = positive.sum().clamp(min=1).to(cls_preds.dtype)
            one_hot = F.one_hot((t.labels - 1).clamp(min=0), self.num_classes).to(cls_preds.dtype)
            one_hot = one_hot * positive[:, None]
            cls_weight = (t.labels >= 0).to(cls_preds.dtype)[:, None]
            cls_loss = cls_loss + (sigmoid_focal_loss(cls_preds[b], one_hot) * cls_weight).sum() / normaliser
            if not bool(positive.any()):
                continue
            anchors, matched = self.anchors[positive], boxes[t.matched_gt[positive]]
            target = encode_residual(matched, anchors, self.encode_angle_by_sincos)
            pred = box_preds[b, positive]
            diff = pred - target
            if not self.encode_angle_by_sincos:
                # sin-difference: the yaw error is sin(pred - target), blind to a pi flip (dir bin's job).
                p, q = pred[:, 6], target[:, 6]
                sin_diff = torch.sin(p) * torch.cos(q) - torch.cos(p) * torch.sin(q)
                diff = torch.cat([diff[:, :6], sin_diff[:, None]], dim=1)
            reg_loss = reg_loss + (smooth_l1(diff) * self.code_weights).sum() / normaliser
            if self.conv_dir is not None:
                offset_rot = limit_period(matched[:, 6] - self.dir_offset, 0.0, 2 * math.pi)
                bins = torch.floor(offset_rot / (2 * math.pi / self.num_dir_bins)).long()
                bins = bins.clamp(0, self.num_dir_bins - 1)
                dir_loss = dir_loss + F.cross_entropy(preds["dir"][b, positive], bins, reduction="sum") / normaliser
        out = {"cls": self.cls_weight * cls_loss / batch_size, "reg": self.reg_weight * reg_loss / batch_size}
        if self.conv_dir is not None:
            out["dir"] = self.dir_weight * dir_loss / batch_size
        return out

    def decode_boxes(self, preds: Dict[str, Tensor]) -> Tensor:
        """All anchors' decoded boxes ``(B, A, 7)`` (direction bin applied, yaw in ``[-pi, pi)``)."""
        boxes = decode_residual(preds["box"], self.anchors, self.encode_angle_by_sincos)
        if self.conv_dir is not None and "dir" in preds:
            period = 2 * math.pi / self.num_dir_bins
            dir_labels = preds["dir"].argmax(dim=-1).to(boxes.dtype)
            rot = limit_period(boxes[..., 6] - self.dir_offset, self.dir_limit_offset, period)
            yaw = rot + self.dir_offset + period * dir_labels
            boxes = torch.cat([boxes[..., :6], yaw[..., None]], dim=-1)
        return torch.cat([boxes[..., :6], limit_period(boxes[..., 6:], 0.5, 2 * math.pi)], dim=-1)

    #: The switches of :meth:`decode` beyond the common settings (``MSSFDetector(decode_options=...)``).
    DECODE_OPTIONS = ("multi_class",)

    @torch.no_grad()
    def decode(
        self,
        preds: Dict[str, Tensor],
        score_threshold: float = 0.1,
        nms_iou: float | None = 0.5,
        max_detections: int = 100,
        multi_class: bool = False,
    ) -> List[dict]:
        """Detections per sample: ``dict(boxes (K, 7), scores (K,), labels (K,))``, best first.

        Default: each anchor is one candidate, labelled with its best class (score = that class's
        probability). ``multi_class=True`` is mmdet3d's ``Anchor3DHead`` (the MSSF authors' MSSF-PP): the
        ``nms_pre`` anchors of highest best-class score, then every (anchor, class) with a probability
        ``> score_threshold`` is a candidate, so one anchor may give a box for two classes (the same box).
        Either way: per-class rotated NMS, then the ``max_detections`` best.
        """
        check_decode_args(score_threshold, nms_iou, max_detections)
        if not isinstance(multi_class, bool):
            raise MSSFError(f"multi_class: expected a bool, got {multi_class!r}")
        boxes = self.decode_boxes(preds)
        probs = torch.sigmoid(preds["cls"])
        scores, labels = probs.max(dim=-1)
        if not multi_class:
            return [
                select_detections(boxes[b], scores[b], labels[b], score_threshold, nms_iou, max_detections,
                                  self.nms_pre)
                for b in range(boxes.shape[0])
            ]
        out = []
        for b in range(boxes.shape[0]):
            top = torch.sort(scores[b], descending=True, stable=True).indices[: self.nms_pre]
            anchor, label = torch.nonzero(probs[b, top] > score_threshold, as_tuple=True)
            anchor = top[anchor]
            out.append(select_detections(boxes[b, anchor], probs[b, anchor, label], label, score_threshold, nms_iou,
                                         max_detections))
        return out
