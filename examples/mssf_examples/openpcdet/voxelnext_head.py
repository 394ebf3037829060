"""OpenPCDet's ``VoxelNeXtHead`` for sparse radar frames: the head ``MSSFVoxelNeXt`` builds for ``DENSE_HEAD.NAME:
VoxelNeXtHead`` (the configs keep the stock name; the parameters and their names are the stock head's).

A radar frame can leave few or no voxels at the head's stride (VoD has frames with no radar return in the
field of view at range). The stock head (OpenPCDet 8caccce) then:

* in training, assigns each box to the nearest voxel of its frame with ``argmin`` over an empty tensor
  (``IndexError: argmin()``), and its regression loss gathers rows of an empty frame (``IndexError``);
* in evaluation, takes ``min(K, n)`` candidates per class of a frame of ``n`` voxels (``K =
  MAX_OBJ_PER_SAMPLE``) and stacks them over the batch (``RuntimeError: stack expects each tensor to be
  equal size``); with a batch of one frame, ``classes x n < K`` fails in a ``view`` and ``n < K <= classes
  x n`` labels the candidates by ``index // K`` instead of ``index // n``: detections of other classes
  get the first class, silently.

Here a frame without voxels gets no target (its boxes have no voxel to be placed on; counted in
``tb_dict['frames_without_voxels']`` and warned about once) and no detection; a batch holding a frame with
fewer voxels than ``K`` is decoded frame by frame, each with ``K = min(K, n)``, by OpenPCDet's own decoder
(the same labels as the batched decoding, boxes and scores up to float32 rounding). Batches where every frame
has at least ``K`` voxels take the stock path unchanged.
"""

from __future__ import annotations

import warnings
from typing import Any, Dict, List

import torch
from easydict import EasyDict
from pcdet.models.dense_heads.voxelnext_head import VoxelNeXtHead
from pcdet.utils import loss_utils

__all__ = ["SparseFrameVoxelNeXtHead"]


class _RegLossSparse(loss_utils.RegLossSparse):
    """``RegLossSparse`` whose frames without voxels contribute zeros (their mask is 0: no target)."""

    def forward(self, output, mask, ind=None, target=None, batch_index=None):
        # the stock gather frame by frame (its boolean selection already reads the batch index back), with
        # zeros for a frame without rows; frames with rows give the stock values
        pred = []
        for b in range(mask.shape[0]):
            rows = output[batch_index == b]
            pred.append(rows[ind[b]] if rows.shape[0] else output.new_zeros((ind.shape[1], output.shape[1])))
        return loss_utils._reg_loss(torch.stack(pred), target, mask)


class SparseFrameVoxelNeXtHead(VoxelNeXtHead):
    """``VoxelNeXtHead`` that trains and evaluates on frames with few or no voxels (module docstring)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.frames_without_voxels = 0  # training frames so far whose boxes got no target
        self._batch_without_voxels = 0

    def build_losses(self):
        super().build_losses()
        self.add_module("reg_loss_func", _RegLossSparse())

    def assign_targets(self, gt_boxes, num_voxels, spatial_indices, spatial_shape):
        empty = [b for b in range(gt_boxes.shape[0]) if spatial_indices[b].shape[0] == 0]
        self._batch_without_voxels = len(empty)
        if empty:
            if not self.frames_without_voxels:  # once per head: VoD has such frames, a log per batch would flood
                boxes = sum(int((gt_boxes[b].abs().sum(-1) > 0).sum()) for b in empty)
                warnings.warn(f"VoxelNeXtHead: {len(empty)} frame(s) of a training batch have no voxel at the head's "
                              f"stride (no radar point in POINT_CLOUD_RANGE); their {boxes} ground-truth box(es) get "
                              "no target and the frame adds nothing to the loss. Counted per batch in "
                              "tb_dict['frames_without_voxels'] (the head's frames_without_voxels: all so far); "
                              "this warning is not repeated", stacklevel=2)
            self.frames_without_voxels += len(empty)
        return super().assign_targets(gt_boxes, num_voxels, spatial_indices, spatial_shape)

    def assign_target_of_single_head(self, num_classes, gt_boxes, num_voxels, spatial_indices, *args, **kwargs):
        if spatial_indices.shape[0] == 0:
            gt_boxes = gt_boxes[:0]  # no voxel to place a box on: zero targets, mask 0
        return super().assign_target_of_single_head(num_classes, gt_boxes, num_voxels, spatial_indices, *args, **kwargs)

    def get_loss(self):
        loss, tb_dict = super().get_loss()
        tb_dict["frames_without_voxels"] = self._batch_without_voxels
        return loss, tb_dict

    def generate_predicted_boxes(self, batch_size, pred_dicts, voxel_indices, spatial_shape):
        k_max = int(self.model_cfg.POST_PROCESSING.MAX_OBJ_PER_SAMPLE)
        # one read-back of the per-frame counts (the stock decoding reads back per frame and in its NMS anyway)
        counts = torch.bincount(voxel_indices[:, 0].long(), minlength=batch_size).tolist()
        if self.double_flip or min(counts[:batch_size]) >= k_max:
            return super().generate_predicted_boxes(batch_size, pred_dicts, voxel_indices, spatial_shape)
        out: List[Dict[str, Any]] = []
        for b in range(batch_size):
            if counts[b] == 0:
                out.append(self._no_detection(pred_dicts[0]))
                continue
            rows = voxel_indices[:, 0] == b
            frame_preds = [{key: value[rows] for key, value in d.items()} for d in pred_dicts]
            frame_indices = voxel_indices[rows].clone()
            frame_indices[:, 0] = 0
            out.append(self._decode_with_k(min(k_max, counts[b]), frame_preds, frame_indices, spatial_shape))
        return out

    def _decode_with_k(self, k, pred_dicts, voxel_indices, spatial_shape):
        """OpenPCDet's decoding of a batch of one frame with ``MAX_OBJ_PER_SAMPLE = k``."""
        cfg = self.model_cfg
        self.model_cfg = EasyDict(cfg)
        self.model_cfg.POST_PROCESSING = EasyDict({**cfg.POST_PROCESSING, "MAX_OBJ_PER_SAMPLE": k})
        try:
            return super().generate_predicted_boxes(1, pred_dicts, voxel_indices, spatial_shape)[0]
        finally:
            self.model_cfg = cfg

    def _no_detection(self, pred_dict):
        width = 7 + (pred_dict["vel"].shape[1] if "vel" in self.separate_head_cfg.HEAD_ORDER else 0)
        ref = pred_dict["center"]
        return {"pred_boxes": ref.new_zeros((0, width)), "pred_scores": ref.new_zeros((0,)),
                "pred_labels": torch.zeros(0, dtype=torch.long, device=ref.device), "pred_ious": []}
