"""``CenterHeadWithoutVelocity``: mmdet3d 1.4's ``CenterHead`` for boxes without velocity (VoD, TJ4DRadSet, KITTI).

mmdet3d 1.4's ``CenterHead`` is written for nuScenes' 9-value boxes: ``get_targets_single`` unpacks
``vx, vy = box[7:]`` (a 7-value box raises) and ``loss_by_feat`` concatenates a ``vel`` branch into the
prediction it compares with the 10-column target. The MSSF authors' CenterPoint configs
(``centerpoint_voxel005_second_secfpn_vod_multimodal``: ``code_size=7``, eight ``code_weights``, no ``vel``
branch) ran on their fork, which edits those two methods in place. This subclass leaves mmdet3d's code
running as it is and gives it what it expects instead:

* the targets of a 7-value box are those of the same box with zero velocity (mmdet3d's own
  ``get_targets_single`` on the padded box);
* ``loss_by_feat`` sees a zero ``vel`` prediction, and the two velocity columns get code weight 0: their
  L1 terms are 0 and the regression loss is the sum over the eight box columns over the same
  ``avg_factor``, which is the authors' loss.

Decoding is mmdet3d's unchanged: without a ``vel`` branch ``CenterPointBBoxCoder`` returns 7-value boxes
(``code_size=7``).
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional

import torch
from mmdet3d.models.dense_heads.centerpoint_head import CenterHead
from mmengine.structures import InstanceData

from mssf_blocks.errors import MSSFError

__all__ = ["CenterHeadWithoutVelocity"]

#: the eight box columns of a velocity-free centre code: offset (2), z (1), log size (3), sin / cos yaw (2)
BOX_COLUMNS = 8


class CenterHeadWithoutVelocity(CenterHead):
    """mmdet3d's ``CenterHead`` on 7-value boxes ``(x, y, z, l, w, h, yaw)``; arguments as ``CenterHead``'s.

    ``common_heads`` must not hold ``vel``; ``train_cfg['code_weights']`` (when given) holds the eight box
    weights, and ``bbox_coder.code_size`` is 7.
    """

    def __init__(self, *args: Any, common_heads: Optional[Dict[str, Any]] = None,
                 train_cfg: Optional[Dict[str, Any]] = None, bbox_coder: Optional[Dict[str, Any]] = None,
                 **kwargs: Any) -> None:
        common_heads = dict(common_heads or {})
        if "vel" in common_heads:
            raise MSSFError("common_heads: CenterHeadWithoutVelocity predicts no velocity; remove 'vel' (or use "
                            "mmdet3d's CenterHead with 9-value boxes)")
        if bbox_coder is not None and int(bbox_coder.get("code_size", 7)) != 7:
            raise MSSFError(f"bbox_coder.code_size: expected 7 (x, y, z, l, w, h, yaw), "
                            f"got {bbox_coder.get('code_size')}")
        if train_cfg is not None and train_cfg.get("code_weights") is not None:
            weights = [float(w) for w in train_cfg["code_weights"]]
            if len(weights) != BOX_COLUMNS:
                raise MSSFError(f"train_cfg.code_weights: expected {BOX_COLUMNS} weights (offset 2, z, log size 3, "
                                f"sin / cos yaw), got {len(weights)}")
            # mmdet3d's loss compares 10 columns (the zero velocity last): those two weigh nothing
            train_cfg = dict(train_cfg, code_weights=weights + [0.0, 0.0])
        super().__init__(*args, common_heads=common_heads, train_cfg=train_cfg, bbox_coder=bbox_coder, **kwargs)

    def get_targets_single(self, gt_instances_3d: InstanceData) -> Any:
        boxes = gt_instances_3d.bboxes_3d
        t = boxes.tensor
        if t.shape[1] == 7:
            padded = InstanceData(labels_3d=gt_instances_3d.labels_3d)
            padded.bboxes_3d = type(boxes)(torch.cat([t, t.new_zeros(len(t), 2)], 1), box_dim=9)
            gt_instances_3d = padded
        elif t.shape[1] != 9:
            raise MSSFError(f"gt_instances_3d.bboxes_3d: expected 7-value boxes, got {t.shape[1]} values")
        return super().get_targets_single(gt_instances_3d)

    def loss_by_feat(self, preds_dicts: Any, batch_gt_instances_3d: List[InstanceData], *args: Any,
                     **kwargs: Any) -> Dict[str, torch.Tensor]:
        for task in preds_dicts:
            reg = task[0]["reg"]
            task[0]["vel"] = reg.new_zeros((reg.shape[0], 2) + tuple(reg.shape[2:]))  # weighs 0 (code_weights)
        return super().loss_by_feat(preds_dicts, batch_gt_instances_3d, *args, **kwargs)
