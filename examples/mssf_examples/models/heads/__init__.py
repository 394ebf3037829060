"""Detection heads of the example detectors: anchor-based (SECOND / PointPillars), dense centre-based
(CenterPoint) and fully sparse centre-based (VoxelNeXt). Each has ``forward``, ``loss(preds, gt_boxes,
gt_labels) -> dict`` and ``decode(preds, score_threshold, nms_iou, max_detections) -> list[dict]``.
"""

from .anchor_head import TJ4D_ANCHOR_SIZES, VOD_ANCHOR_SIZES, AnchorHead, make_anchors
from .center_head import CenterHead
from .common import BEVGrid
from .sparse_center_head import SparseCenterHead

__all__ = [
    "AnchorHead",
    "CenterHead",
    "SparseCenterHead",
    "BEVGrid",
    "make_anchors",
    "VOD_ANCHOR_SIZES",
    "TJ4D_ANCHOR_SIZES",
]
