"""Dense centre-based BEV head (CenterPoint, Yin et al., CVPR 2021).

A shared 3x3 conv, then one small conv branch per output: a ``K``-class heatmap (CenterNet focal loss
against Gaussian targets), the sub-cell centre offset (2), the centre ``z`` (1), log sizes (3) and
``(sin yaw, cos yaw)`` (2), regressed with L1 at the centre cell of each box. Decoding takes the
top-scoring local maxima of the heatmap (3x3 max-pool "NMS"), reads the regression there, and can apply
a rotated BEV NMS on top.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.errors import MSSFError

from ..ops.boxes import CENTER_CODE_SIZE, decode_center
from ..ops.targets import center_targets
from .common import BEVGrid, check_decode_args, check_gt_lists, gaussian_focal_loss, select_detections

__all__ = ["CenterHead", "REGRESSION_BRANCHES"]

#: Regression branches and their channels, concatenated in this order into the 8-value centre code.
REGRESSION_BRANCHES = (("center", 2), ("center_z", 1), ("dim", 3), ("rot", 2))


class _CenterHeadBase(nn.Module):
    """What the dense and the sparse centre heads share: arguments, checks, layers, loss weighting.

    Subclasses set ``_layer(cin, cout, bias, factory)`` (a 3x3 conv or a linear layer) and
    ``_shared_name`` (the attribute of the shared layer, kept for state_dict compatibility).
    """

    _shared_name = "shared"

    @staticmethod
    def _layer(cin: int, cout: int, bias: bool, factory: dict) -> nn.Module:
        raise NotImplementedError

    def _hidden(self, cin: int, hidden: int, norm_layer, factory: dict) -> list:
        layers: list = [self._layer(cin, hidden, norm_layer is None, factory)]
        if norm_layer is not None:
            layers.append(norm_layer(hidden, **factory))
        return layers + [nn.ReLU(inplace=True)]

    def _branch(self, cin: int, cout: int, hidden: int, norm_layer, factory: dict) -> nn.Sequential:
        return nn.Sequential(*self._hidden(cin, hidden, norm_layer, factory), self._layer(hidden, cout, True, factory))

    def __init__(
        self,
        in_channels: int,
        grid: BEVGrid,
        num_classes: int,
        head_channels: int,
        norm_layer: Callable[..., nn.Module] | None,
        min_overlap: float,
        min_radius: int,
        cls_weight: float,
        reg_weight: float,
        code_weights: Sequence[float] | None,
        nms_pre: int,
        device=None,
        dtype=None,
    ) -> None:
        super().__init__()
        if not isinstance(grid, BEVGrid):
            raise MSSFError(f"grid: expected a BEVGrid, got {type(grid).__name__}")
        for name, value in (("in_channels", in_channels), ("num_classes", num_classes),
                            ("head_channels", head_channels)):
            check_positive_int(value, name)
        if not 0.0 < min_overlap < 1.0:
            raise MSSFError(f"min_overlap: expected a value in (0, 1), got {min_overlap}")
        code_weights = [1.0] * CENTER_CODE_SIZE if code_weights is None else list(map(float, code_weights))
        if len(code_weights) != CENTER_CODE_SIZE:
            raise MSSFError(f"code_weights: expected {CENTER_CODE_SIZE} values, got {len(code_weights)}")
        self.grid, self.in_channels, self.num_classes = grid, in_channels, num_classes
        self.min_overlap, self.min_radius = min_overlap, min_radius
        self.cls_weight, self.reg_weight, self.nms_pre = cls_weight, reg_weight, nms_pre
        factory = {"device": device, "dtype": dtype}
        self.register_buffer("code_weights", torch.tensor(code_weights, **factory), persistent=False)
        setattr(self, self._shared_name, nn.Sequential(*self._hidden(in_channels, head_channels, norm_layer, factory)))
        self.heads = nn.ModuleDict({"hm": self._branch(head_channels, num_classes, head_channels, norm_layer, factory)})
        for name, channels in REGRESSION_BRANCHES:
            self.heads[name] = self._branch(head_channels, channels, head_channels, norm_layer, factory)
        nn.init.constant_(self.heads["hm"][-1].bias, -2.19)  # CenterPoint's heatmap prior (p ~ 0.1)

    def extra_repr(self) -> str:
        return f"in_channels={self.in_channels}, num_classes={self.num_classes}, grid={self.grid}"

    def _codes(self, preds: Dict[str, Tensor]) -> Tensor:
        """The 8-value centre code, concatenated along dim 1: ``(B, 8, ny, nx)`` or ``(M, 8)``."""
        return torch.cat([preds[name] for name, _ in REGRESSION_BRANCHES], dim=1)

    def _weighted_losses(self, hm: Tensor, heatmap: Tensor, pred_rows: List[Tensor],
                         target_rows: List[Tensor]) -> Dict[str, Tensor]:
        """Gaussian focal heatmap loss and L1 regression over the boxes' rows (normalised by their number)."""
        cls_loss = gaussian_focal_loss(hm, heatmap)
        pred, target = torch.cat(pred_rows), torch.cat(target_rows)
        reg_loss = ((pred - target).abs() * self.code_weights).sum() / max(1, target.shape[0])
        return {"cls": self.cls_weight * cls_loss, "reg": self.reg_weight * reg_loss}


class CenterHead(_CenterHeadBase):
    """CenterPoint head on a dense BEV map.

    Args:
        in_channels: channels ``C`` of the BEV map.
        grid: the map's :class:`BEVGrid` (the head's stride is folded into its cell size).
        num_classes: ``K``.
        head_channels: width of the shared conv and of every branch.
        norm_layer: normalisation type after each hidden conv (``None`` for none).
        min_overlap, min_radius: Gaussian radius settings (CenterPoint: 0.1, 2).
        cls_weight, reg_weight: loss weights (OpenPCDet KITTI config: 1, 2).
        code_weights: 8 weights of ``(off_x, off_y, z, log dx, log dy, log dz, sin, cos)``.
        nms_pre: heatmap peaks taken per sample before the score threshold and NMS.
        device, dtype: for the parameters.

    Shape:
        ``forward(bev (B, C, ny, nx)) -> dict(hm (B, K, ny, nx), center (B, 2, ny, nx),
        center_z (B, 1, ny, nx), dim (B, 3, ny, nx), rot (B, 2, ny, nx))``.
    """

    _shared_name = "shared_conv"

    @staticmethod
    def _layer(cin: int, cout: int, bias: bool, factory: dict) -> nn.Module:
        return nn.Conv2d(cin, cout, 3, padding=1, bias=bias, **factory)

    def __init__(
        self,
        in_channels: int,
        grid: BEVGrid,
        num_classes: int,
        head_channels: int = 64,
        norm_layer: Callable[..., nn.Module] | None = nn.BatchNorm2d,
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

    def forward(self, bev: Tensor) -> Dict[str, Tensor]:
        """Heatmap logits and regression maps from ``bev (B, C, ny, nx)``."""
        check_shape(bev, "bev", ("B", self.in_channels, self.grid.ny, self.grid.nx))
        check_floating(bev, "bev")
        x = self.shared_conv(bev)
        return {name: head(x) for name, head in self.heads.items()}

    def loss(self, preds: Dict[str, Tensor], gt_boxes: List[Tensor], gt_labels: List[Tensor]) -> Dict[str, Tensor]:
        """CenterNet focal heatmap loss (normalised by the batch's peaks) and L1 regression at box centres
        (normalised by the batch's number of boxes).

        Returns:
            ``dict(cls, reg)`` scalar tensors (already weighted).
        """
        hm = preds["hm"]
        batch_size = hm.shape[0]
        check_gt_lists(gt_boxes, gt_labels, batch_size, self.num_classes)
        codes = self._codes(preds)
        heatmaps, pred_rows, target_rows = [], [], []
        for b in range(batch_size):
            t = center_targets(
                gt_boxes[b].to(device=hm.device, dtype=hm.dtype), gt_labels[b].to(hm.device).long(),
                self.grid, self.num_classes, self.min_overlap, self.min_radius,
            )
            heatmaps.append(t.heatmap)
            pred_rows.append(codes[b, :, t.cell_index[:, 1], t.cell_index[:, 0]].T)
            target_rows.append(t.regression)
        return self._weighted_losses(hm, torch.stack(heatmaps), pred_rows, target_rows)

    @torch.no_grad()
    def decode(
        self,
        preds: Dict[str, Tensor],
        score_threshold: float = 0.1,
        nms_iou: float | None = 0.5,
        max_detections: int = 100,
    ) -> List[dict]:
        """Detections per sample: ``dict(boxes (K, 7), scores (K,), labels (K,))``, best first."""
        check_decode_args(score_threshold, nms_iou, max_detections)
        heat = torch.sigmoid(preds["hm"])
        batch_size, num_classes, ny, nx = heat.shape
        peaks = heat * (F.max_pool2d(heat, 3, stride=1, padding=1) == heat)
        codes = self._codes(preds).flatten(2)  # (B, 8, ny*nx)
        k = min(self.nms_pre, num_classes * ny * nx)
        scores, flat = peaks.flatten(1).topk(k, dim=1)
        labels, cells = flat // (ny * nx), flat % (ny * nx)
        out = []
        for b in range(batch_size):
            cell_index = torch.stack([cells[b] % nx, cells[b] // nx], dim=-1)
            boxes = decode_center(codes[b][:, cells[b]].T, cell_index, (self.grid.cell_x, self.grid.cell_y),
                                  (self.grid.x_min, self.grid.y_min))
            out.append(select_detections(boxes, scores[b], labels[b], score_threshold, nms_iou, max_detections))
        return out
