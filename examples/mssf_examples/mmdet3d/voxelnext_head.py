"""``MSSFVoxelNeXtHead``: VoxelNeXt's fully sparse head for mmdetection3d 1.x (which has none), the head of MSSF-V.

It reads the sparse BEV that ``MSSFSparseEncoder(layout="VoxelResBackBone8xVoxelNeXt")`` returns (``[SparseConvTensor]``
with indices ``(b, y, x)`` at stride ``out_size_factor``) and computes what OpenPCDet's ``VoxelNeXtHead`` and the
MSSF authors' ``VoxelNeXtHead`` (``EricLiuhhh/MSSF``, mmdet3d) compute, from the examples' pieces:

* layers: :class:`~mssf_examples.models.heads.authors.AuthorsVoxelNeXtHead` (per output a 3 x 3 submanifold
  convolution with bias, BN1d, ReLU, a 1 x 1 submanifold convolution; spconv's parameters, plain torch), branches
  ``hm, center, center_z, dim, rot`` (the authors' ``heatmap, reg, height, dim, rot``; ``rot`` is ``(sin, cos)``
  as theirs, OpenPCDet's ``(cos, sin)``);
* targets: :func:`~mssf_examples.models.ops.voxelnext_targets.voxelnext_targets` (theirs);
* losses: the CenterNet focal loss over all voxels of the batch divided by its positives (``loss_heatmap``, times
  ``cls_weight``) and the L1 regression at the positives, times ``code_weights``, divided by the batch's boxes
  (``loss_bbox``, times ``loc_weight``): OpenPCDet's ``FocalLossSparse`` / ``RegLossSparse``; the authors' with
  weights 1;
* decoding: :meth:`~mssf_examples.models.heads.SparseCenterHead.decode`: the ``max_num`` best (voxel, class)
  scores of each sample, ``> score_threshold``, centres inside ``post_center_limit_range``, one rotated BEV NMS
  over all classes (``nms_thr``), the ``post_max_size`` best; boxes are returned as the samples'
  ``box_type_3d`` (``LiDARInstance3DBoxes``, bottom centre, as the authors' ``z - h / 2``).

Registered in ``mmdet3d.registry.MODELS`` by :mod:`mssf_examples.mmdet3d.plugin`.
"""

from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Sequence

import torch
from mmengine.model import BaseModule
from mmengine.structures import InstanceData
from torch import Tensor

from mssf_blocks.errors import MSSFError

from ..models.heads.authors import AuthorsVoxelNeXtHead
from ..models.heads.common import BEVGrid
from ..models.ops.voxelnext_targets import voxelnext_targets

__all__ = ["MSSFVoxelNeXtHead", "TRAIN_CFG", "TEST_CFG"]

#: ``train_cfg.pts`` keys the head reads, and their defaults (VoxelNeXt's; the authors' names)
TRAIN_CFG = {"gaussian_overlap": 0.1, "min_radius": 2, "max_objs": 500, "code_weights": [1.0] * 8}
#: ``test_cfg.pts`` keys the head reads, and their defaults (the authors' MSSF-V ``vx_mm_r50_ablation_n2m4``)
TEST_CFG = {"max_num": 500, "score_threshold": 0.1, "nms_thr": 0.2, "post_max_size": 83,
            "post_center_limit_range": None}


def _settings(cfg: Optional[Dict[str, Any]], defaults: Dict[str, Any], name: str) -> Dict[str, Any]:
    cfg = dict(cfg or {})
    unknown = sorted(set(cfg) - set(defaults))
    if unknown:
        raise MSSFError(f"{name}: unknown keys {unknown}; expected among {sorted(defaults)}")
    return {**defaults, **cfg}


def bev_grid(point_cloud_range: Sequence[float], voxel_size: Sequence[float], out_size_factor: int) -> BEVGrid:
    """The BEV grid of the encoder's sparse BEV: ``ceil(n / out_size_factor)`` cells of ``voxel * out_size_factor``
    metres from the range's minimum (spconv's stride-2 convolutions round up)."""
    r, v = [float(x) for x in point_cloud_range], [float(x) for x in voxel_size]
    if len(r) != 6 or len(v) < 2:
        raise MSSFError(f"point_cloud_range, voxel_size: expected 6 and 3 values, got {point_cloud_range!r}, "
                        f"{voxel_size!r}")
    cells = [math.ceil(round((r[3 + i] - r[i]) / v[i]) / out_size_factor) for i in range(2)]
    cell = [v[i] * out_size_factor for i in range(2)]
    return BEVGrid(r[0], r[1], r[0] + cells[0] * cell[0], r[1] + cells[1] * cell[1], cells[1], cells[0])


class MSSFVoxelNeXtHead(BaseModule):
    """VoxelNeXt head (one task, all classes) with mmdet3d's head contract (module docstring).

    Args:
        in_channels: channels of the sparse BEV (the encoder's ``out_channels``; the paper's 256).
        num_classes: ``K`` (label ``k`` is the dataset's class ``k``).
        point_cloud_range, voxel_size: the data preprocessor's grid.
        out_size_factor: stride of the sparse BEV (VoxelNeXt: 8).
        head_channels: the branches' hidden width (the authors' ``share_conv_channel``, 256).
        kernel_size: of the branches' first submanifold convolution: 3 (the authors', VoxelNeXt's) or 1
            (OpenPCDet's ``KERNEL_SIZE_HEAD: 1`` in this project's OpenPCDet config).
        cls_weight, loc_weight: loss weights (OpenPCDet's ``cls_weight`` / ``loc_weight``; the authors' 1 and 1).
        train_cfg: keys of :data:`TRAIN_CFG` (``train_cfg.pts`` of the model); ``code_weights`` in the order
            ``(dx, dy, z, log l, log w, log h, sin, cos)`` (OpenPCDet's configs end in ``cos, sin``).
        test_cfg: keys of :data:`TEST_CFG` (``test_cfg.pts``); ``post_center_limit_range`` ``None``: no filter.
    """

    def __init__(self, in_channels: int, num_classes: int, point_cloud_range: Sequence[float],
                 voxel_size: Sequence[float], out_size_factor: int = 8, head_channels: int = 256, kernel_size: int = 3,
                 cls_weight: float = 1.0, loc_weight: float = 1.0, train_cfg: Optional[dict] = None,
                 test_cfg: Optional[dict] = None, init_cfg: Optional[dict] = None) -> None:
        super().__init__(init_cfg=init_cfg)
        self.train_settings = _settings(train_cfg, TRAIN_CFG, "train_cfg")
        self.test_settings = _settings(test_cfg, TEST_CFG, "test_cfg")
        self.grid = bev_grid(point_cloud_range, voxel_size, int(out_size_factor))
        self.num_classes = int(num_classes)
        self.net = AuthorsVoxelNeXtHead(int(in_channels), self.grid, self.num_classes, head_channels=int(head_channels),
                                        kernel_size=int(kernel_size),
                                        cls_weight=float(cls_weight), reg_weight=float(loc_weight),
                                        code_weights=self.train_settings["code_weights"],
                                        nms_pre=int(self.test_settings["max_num"]))

    def forward(self, feats: Sequence[Any], batch_size: Optional[int] = None) -> Dict[str, Any]:
        """Per-voxel outputs (``hm (M, K)`` logits, ``center, center_z, dim, rot``, ``coords (M, 3)`` (b, y, x),
        ``batch_size``) of ``feats = [SparseConvTensor]`` (2-d indices)."""
        if not isinstance(feats, (list, tuple)) or len(feats) != 1 or not hasattr(feats[0], "indices"):
            raise MSSFError(f"feats: expected [SparseConvTensor] (the sparse BEV of MSSFSparseEncoder with layout "
                            f"'VoxelResBackBone8xVoxelNeXt'), got {type(feats).__name__} of "
                            f"{[type(f).__name__ for f in feats] if isinstance(feats, (list, tuple)) else feats!r}")
        x = feats[0]
        if x.indices.shape[1] != 3:
            raise MSSFError(f"feats[0].indices: expected (M, 3) (b, y, x) at the BEV stride, got "
                            f"{tuple(x.indices.shape)} (a 3-d sparse tensor: use the VoxelNeXt layout, whose encoder "
                            "merges the stages into a BEV)")
        batch_size = max(int(x.batch_size), int(batch_size or 0))
        return self.net(x.features, x.indices, batch_size)

    def loss(self, pts_feats: Sequence[Any], batch_data_samples: List[Any], **kwargs: Any) -> Dict[str, Tensor]:
        preds = self(pts_feats, len(batch_data_samples))
        return self.loss_by_feat(preds, [s.gt_instances_3d for s in batch_data_samples])

    def targets(self, preds: Dict[str, Any], batch_gt_instances_3d: List[InstanceData]):
        """``(heatmap (M, K), [rows of the positives per sample], [regression targets per sample])``."""
        hm, coords = preds["hm"], preds["coords"]
        t = self.train_settings
        heatmap = torch.zeros_like(hm)
        rows_out, targets = [], []
        for b, gt in enumerate(batch_gt_instances_3d):
            boxes = gt.bboxes_3d
            # gravity centre: the head regresses the centre z (the boxes' tensor holds the bottom)
            boxes = torch.cat([boxes.gravity_center, boxes.tensor[:, 3:7]], 1).to(device=hm.device, dtype=hm.dtype)
            rows = torch.nonzero(coords[:, 0] == b).flatten()
            tb = voxelnext_targets(boxes, gt.labels_3d.to(hm.device).long(), coords[rows][:, [2, 1]].long(), self.grid,
                                   self.num_classes, float(t["gaussian_overlap"]), int(t["min_radius"]),
                                   int(t["max_objs"]))
            heatmap[rows] = tb.heatmap
            rows_out.append(rows[tb.voxel_index])
            targets.append(tb.regression)
        return heatmap, rows_out, targets

    def loss_by_feat(self, preds: Dict[str, Any], batch_gt_instances_3d: List[InstanceData],
                     *args: Any, **kwargs: Any) -> Dict[str, Tensor]:
        """``dict(loss_heatmap, loss_bbox)`` (weighted, see the module docstring)."""
        heatmap, rows, targets = self.targets(preds, batch_gt_instances_3d)
        codes = self.net._codes(preds)
        losses = self.net._weighted_losses(preds["hm"], heatmap, [codes[r] for r in rows], targets)
        return {"loss_heatmap": losses["cls"], "loss_bbox": losses["reg"]}

    def predict(self, pts_feats: Sequence[Any], batch_data_samples: List[Any], **kwargs: Any) -> List[InstanceData]:
        preds = self(pts_feats, len(batch_data_samples))
        return self.predict_by_feat(preds, [s.metainfo for s in batch_data_samples])

    def predict_by_feat(self, preds: Dict[str, Any], batch_input_metas: List[dict], *args: Any,
                        **kwargs: Any) -> List[InstanceData]:
        """Per sample ``InstanceData(bboxes_3d, scores_3d, labels_3d)``, best first (module docstring)."""
        s = self.test_settings
        dets = self.net.decode(preds, float(s["score_threshold"]), float(s["nms_thr"]), int(s["post_max_size"]),
                               class_agnostic_nms=True, center_range=s["post_center_limit_range"])
        out = []
        for d, meta in zip(dets, batch_input_metas):
            boxes = d["boxes"].clone()
            boxes[:, 2] -= boxes[:, 5] / 2  # centre z -> the bottom centre of mmdet3d's boxes
            box_type = meta.get("box_type_3d")
            if box_type is None:
                from mmdet3d.structures import LiDARInstance3DBoxes as box_type
            res = InstanceData()
            res.bboxes_3d = box_type(boxes, box_dim=7)
            res.scores_3d = d["scores"]
            res.labels_3d = d["labels"]
            out.append(res)
        return out
