"""Fully sparse centre head (VoxelNeXt, Chen et al., CVPR 2023).

Predicts the CenterPoint outputs directly on the non-empty BEV voxels ``(features (M, C), coords (M, 3)
(b, y, x))`` at the head's stride, with no dense map. Targets: the voxel whose cell centre is nearest to a
box centre is that box's positive (heatmap 1) and carries its regression (offset from that voxel's
integer index, which may exceed one cell when the centre itself is empty); the other voxels take the
dense Gaussian heatmap's value at their cell as the negative down-weighting. Decoding reads the top
voxel scores of each sample and applies rotated BEV NMS (there is no max-pool over a dense map).

VoxelNeXt's branches are 3x3 submanifold convolutions; ours are per-voxel (1x1) layers so the head has
no spconv dependency and its receptive field comes from the backbone.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Sequence

import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_dtype, check_floating, check_shape
from mssf_blocks.errors import MSSFError

from ..ops.boxes import decode_center
from ..ops.targets import sparse_center_targets
from .center_head import _CenterHeadBase
from .common import BEVGrid, check_center_range, check_decode_args, check_gt_lists, select_detections

__all__ = ["SparseCenterHead"]


class SparseCenterHead(_CenterHeadBase):
    """VoxelNeXt-style sparse centre head.

    Args:
        in_channels: channels ``C`` of the voxel features.
        grid: :class:`BEVGrid` of the voxels' BEV indices (``ny x nx`` = sparse spatial shape at the
            head's stride, cell size = voxel size x stride).
        num_classes: ``K``.
        head_channels: hidden width.
        norm_layer: normalisation after each hidden layer (``nn.BatchNorm1d`` or ``None``).
        min_overlap, min_radius, cls_weight, reg_weight, code_weights, nms_pre: as
            :class:`~mssf_examples.models.heads.center_head.CenterHead`.
        device, dtype: for the parameters.

    Shape:
        ``forward(features (M, C), coords (M, 3) int (b, y, x), batch_size) -> dict(hm (M, K),
        center (M, 2), center_z (M, 1), dim (M, 3), rot (M, 2), coords (M, 3), batch_size)``.
    """

    _shared_name = "shared"

    @staticmethod
    def _layer(cin: int, cout: int, bias: bool, factory: dict) -> nn.Module:
        return nn.Linear(cin, cout, bias=bias, **factory)

    def __init__(
        self,
        in_channels: int,
        grid: BEVGrid,
        num_classes: int,
        head_channels: int = 64,
        norm_layer: Callable[..., nn.Module] | None = nn.BatchNorm1d,
        min_overlap: float = 0.1,
        min_radius: int = 2,
        cls_weight: float = 1.0,
        reg_weight: float = 2.0,
        code_weights: Sequence[float] | None = None,
        nms_pre: int = 500,
        device=None,
        dtype=None,
    ) -> None:
        super().__init__(in_channels, grid, num_classes, head_channels, norm_layer, min_overlap, min_radius,
                         cls_weight, reg_weight, code_weights, nms_pre, device, dtype)

    def forward(self, features: Tensor, coords: Tensor, batch_size: int) -> Dict[str, object]:
        """Per-voxel heatmap logits and regression from ``features (M, C)`` at ``coords (M, 3)`` (b, y, x)."""
        self._check_inputs(features, coords, batch_size)
        x = self.shared(features)
        out: Dict[str, object] = {name: head(x) for name, head in self.heads.items()}
        out["coords"] = coords
        out["batch_size"] = batch_size
        return out

    def _check_inputs(self, features: Tensor, coords: Tensor, batch_size: int) -> None:
        dims: dict = {}
        check_shape(features, "features", ("M", self.in_channels), dims)
        check_shape(coords, "coords", ("M", 3), dims)
        check_floating(features, "features")
        check_dtype(coords, "coords", (torch.int32, torch.int64))
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size <= 0:
            raise MSSFError(f"batch_size: expected a positive int, got {batch_size!r}")
        if coords.numel():
            upper = torch.tensor([batch_size, self.grid.ny, self.grid.nx], device=coords.device)
            if bool((coords < 0).any()) or bool((coords >= upper).any()):
                lo, hi = coords.min(0).values.tolist(), coords.max(0).values.tolist()
                raise MSSFError(
                    f"coords: expected (b, y, x) in [0, {batch_size}) x [0, {self.grid.ny}) x [0, {self.grid.nx}), "
                    f"got per-column min {lo} and max {hi}"
                )

    def loss(self, preds: Dict[str, object], gt_boxes: List[Tensor], gt_labels: List[Tensor]) -> Dict[str, Tensor]:
        """Focal heatmap loss over all voxels and L1 regression at each box's voxel.

        Returns:
            ``dict(cls, reg)`` scalar tensors (already weighted).
        """
        hm, coords, batch_size = preds["hm"], preds["coords"], preds["batch_size"]
        check_gt_lists(gt_boxes, gt_labels, batch_size, self.num_classes)
        codes = self._codes(preds)
        heatmap = torch.zeros_like(hm)
        pred_rows, target_rows = [], []
        for b in range(batch_size):
            rows = torch.nonzero(coords[:, 0] == b).flatten()
            t = sparse_center_targets(
                gt_boxes[b].to(device=hm.device, dtype=hm.dtype), gt_labels[b].to(hm.device).long(),
                coords[rows][:, [2, 1]].long(), self.grid, self.num_classes, self.min_overlap, self.min_radius,
            )
            heatmap[rows] = t.heatmap
            pred_rows.append(codes[rows[t.voxel_index]])
            target_rows.append(t.regression)
        return self._weighted_losses(hm, heatmap, pred_rows, target_rows)

    #: The switches of :meth:`decode` beyond the common settings (``MSSFDetector(decode_options=...)``).
    DECODE_OPTIONS = ("class_agnostic_nms", "center_range")

    @torch.no_grad()
    def decode(
        self,
        preds: Dict[str, object],
        score_threshold: float = 0.1,
        nms_iou: float | None = 0.5,
        max_detections: int = 100,
        class_agnostic_nms: bool = False,
        center_range: Sequence[float] | None = None,
    ) -> List[dict]:
        """Detections per sample: ``dict(boxes (K, 7), scores (K,), labels (K,))``, best first.

        The ``nms_pre`` best (voxel, class) scores, ``> score_threshold``, rotated NMS (per class, or over
        all classes with ``class_agnostic_nms=True``), the ``max_detections`` best. ``center_range``
        ``(x0, y0, z0, x1, y1, z1)`` drops, before NMS, boxes whose centre lies outside it (bounds
        inclusive). The MSSF authors' ``VoxelNeXtHead`` has both switches on (their point-cloud range).
        """
        check_decode_args(score_threshold, nms_iou, max_detections)
        if not isinstance(class_agnostic_nms, bool):
            raise MSSFError(f"class_agnostic_nms: expected a bool, got {class_agnostic_nms!r}")
        if center_range is not None:
            check_center_range(center_range)
        hm, coords, batch_size = preds["hm"], preds["coords"], preds["batch_size"]
        heat = torch.sigmoid(hm)
        boxes_all = decode_center(
            self._codes(preds), coords[:, [2, 1]].long(), (self.grid.cell_x, self.grid.cell_y),
            (self.grid.x_min, self.grid.y_min),
        )
        out = []
        for b in range(batch_size):
            rows = torch.nonzero(coords[:, 0] == b).flatten()
            flat = heat[rows].flatten()
            k = min(self.nms_pre, flat.numel())
            scores, idx = flat.topk(k)
            voxel, labels = idx // self.num_classes, idx % self.num_classes
            boxes = boxes_all[rows[voxel]]
            out.append(select_detections(boxes, scores, labels, score_threshold, nms_iou, max_detections,
                                         class_agnostic_nms=class_agnostic_nms, center_range=center_range))
        return out
