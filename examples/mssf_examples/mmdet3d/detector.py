"""``MSSFDetector``: an mmdet3d MVX detector whose middle encoder is an MSSF fusion backbone.

Registered in ``mmdet3d.registry.MODELS`` by :mod:`mssf_examples.mmdet3d.plugin` (the encoders it runs
are the library's, registered by :mod:`mssf_blocks.integrations.mmdet3d_plugin`). This module imports
``mmdet3d.models`` at import time (mmcv's compiled ops).

What it changes against ``MVXTwoStageDetector``:

* ``extract_pts_feat`` calls the middle encoder (:class:`MSSFSparseEncoder` after voxelisation and the
  voxel encoder, or :class:`MSSFPillarEncoder` on the points) with the points, the image neck's levels
  and the metainfo, then ``pts_backbone`` / ``pts_neck`` when configured;
* ``loss`` returns the box head's losses and the semantic head's focal loss as ``loss_seg`` (times
  ``seg_loss_weight``);
* the image branch is frozen (``freeze_img=True``: no gradients, BN statistics fixed), the paper's setting
  with a pretrained image backbone loaded through the backbone's / neck's ``init_cfg`` or ``load_from``; a
  frozen image weight that no checkpoint ever filled is refused at the first training step
  (:func:`check_image_weights`: a random, frozen ResNet would otherwise train without a word);
* clear errors instead of silent fallbacks: fusion blocks without an image branch or without images, an
  image neck whose levels / channels differ from ``image_channels``, metainfo without ``lidar2img``, a
  voxel encoder whose feature count differs from the encoder's ``in_channels``, a model without a box head.
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence

import torch
from torch import Tensor

from mmdet3d.models.detectors.mvx_two_stage import MVXTwoStageDetector

from mssf_blocks.errors import MSSFError

__all__ = ["MSSFDetector", "check_image_weights", "frozen_image_message"]

_IMAGE_PARTS = ("img_backbone", "img_neck")


def _record_loaded(module: torch.nn.Module, state_dict: Dict[str, Any], prefix: str, *args: Any) -> None:
    """``load_state_dict`` pre-hook of the image backbone / neck: remember which of its parameters a checkpoint
    gave. Runs inside ``_load_from_state_dict``, so torch's loader and mmengine's (``load_from``, ``--resume``,
    ``init_cfg=dict(type="Pretrained")``) all pass here; the names live on the module (deep copies keep them)."""
    loaded = module.__dict__.setdefault("_mssf_loaded", set())
    loaded.update(n for n, _ in module.named_parameters() if prefix + n in state_dict)


def frozen_image_message(parts: Dict[str, str], by_flag: bool) -> str:
    """The error for frozen image weights that no checkpoint filled; ``parts``: module name -> what is unloaded."""
    what = "; ".join(f"{k}: {v}" for k, v in parts.items())
    frozen = ("model.freeze_img=True (the paper's setting: a pre-trained, frozen image branch)" if by_flag else
              "the modules' own settings (e.g. img_backbone.frozen_stages, norm_cfg requires_grad=False)")
    return (f"{', '.join(parts)}: frozen by {frozen} but never loaded from a checkpoint ({what}): training would "
            "fuse the features of a random, frozen network. Either load pre-trained weights: "
            "model.img_backbone.init_cfg=dict(type='Pretrained', checkpoint=..., prefix='backbone.') and "
            "model.img_neck.init_cfg=dict(type='Pretrained', checkpoint=..., prefix='neck.') (the paper's HTC "
            "R-50-FPN; `python -m mssf_examples.mmdet3d train --image-checkpoint PATH` sets both), or load_from / "
            "--resume a checkpoint of this model; or train the branch: model.freeze_img=False "
            "(docs/frameworks.md, mmdetection3d)")


def check_image_weights(model: "MSSFDetector") -> None:
    """Refuse frozen image weights (``requires_grad=False`` matrices and kernels, ``dim >= 2``) that no checkpoint
    filled. Run at the first training step: mmengine builds the model, then ``init_weights`` (``init_cfg``), then
    loads ``load_from`` / the resumed checkpoint, so before that step nothing tells whether weights will come.
    Norm scales and biases (1-d) are not counted: frozen BN at its initial values is a setting of its own."""
    parts = {}
    for name in _IMAGE_PARTS:
        module = getattr(model, name, None)
        if module is None:
            continue
        loaded = module.__dict__.get("_mssf_loaded", set())
        frozen = [n for n, p in module.named_parameters() if not p.requires_grad and p.dim() >= 2]
        unloaded = [n for n in frozen if n not in loaded]
        if unloaded:
            parts[name] = f"{len(unloaded)} of its {len(frozen)} frozen weight tensors, e.g. {unloaded[0]}"
    if parts:
        raise MSSFError(frozen_image_message(parts, model.freeze_img))


def _neck_levels(neck: Any) -> Optional[List[int]]:
    """``[channels] * levels`` of an mmdet ``FPN``-like neck (``None`` when it does not say)."""
    out, num = getattr(neck, "out_channels", None), getattr(neck, "num_outs", None)
    if isinstance(out, int) and isinstance(num, int):
        return [out] * num
    return None


class MSSFDetector(MVXTwoStageDetector):
    """MVX detector with an MSSF middle encoder (``MSSFSparseEncoder`` or ``MSSFPillarEncoder``).

    Args:
        seg_loss_weight: weight of the semantic head's focal loss (``loss_seg``); the paper's 1.0.
        freeze_img: keep the image backbone and neck frozen (``requires_grad=False``, eval mode); their weights
            must then come from a checkpoint (``init_cfg``, ``load_from``, ``resume``): training refuses them
            otherwise (:func:`check_image_weights`).
        **kwargs: ``MVXTwoStageDetector``'s arguments.
    """

    def __init__(self, seg_loss_weight: float = 1.0, freeze_img: bool = True, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        if not self.with_pts_bbox:
            raise MSSFError("pts_bbox_head: MSSFDetector needs a box head (got none); without it loss() would be empty")
        enc = getattr(self, "pts_middle_encoder", None)
        if enc is None or not hasattr(enc, "num_fusion_blocks"):
            raise MSSFError(f"pts_middle_encoder: expected MSSFSparseEncoder or MSSFPillarEncoder, got "
                            f"{type(enc).__name__ if enc is not None else None}")
        self.seg_loss_weight = float(seg_loss_weight)
        if self.seg_loss_weight < 0:
            raise MSSFError(f"seg_loss_weight: expected >= 0, got {seg_loss_weight}")
        self.freeze_img = bool(freeze_img)
        self._consumes_points = bool(getattr(enc, "consumes_points", False))
        nfb = enc.num_fusion_blocks
        if nfb and not (self.with_img_backbone and self.with_img_neck):
            raise MSSFError(f"img_backbone, img_neck: the encoder has {nfb} fusion blocks and needs both; "
                            "for a radar-only model set num_fusion_blocks=0")
        if not nfb and (self.with_img_backbone or self.with_img_neck):
            raise MSSFError("img_backbone, img_neck: given, but the encoder has no fusion blocks (num_fusion_blocks=0); "
                            "drop them for the radar-only model")
        if nfb:
            expected = getattr(enc, "image_channels", None)
            levels = _neck_levels(self.img_neck)
            if expected is not None and levels is not None and levels != expected:
                raise MSSFError(f"pts_middle_encoder.image_channels: expected the image neck's levels {levels} "
                                f"(out_channels x num_outs), got {expected}")
        vfe = getattr(self, "pts_voxel_encoder", None)
        if self._consumes_points and vfe is not None:
            raise MSSFError(f"pts_voxel_encoder: {type(enc).__name__} takes the points itself; remove the voxel encoder")
        if not self._consumes_points:
            if vfe is None:
                raise MSSFError(f"pts_voxel_encoder: {type(enc).__name__} needs voxel features (e.g. HardSimpleVFE)")
            nf = getattr(vfe, "num_features", None)
            if nf is not None and int(nf) != enc.in_channels:
                raise MSSFError(f"pts_voxel_encoder.num_features: expected the middle encoder's in_channels "
                                f"{enc.in_channels}, got {nf}")
        for name in _IMAGE_PARTS:
            m = getattr(self, name, None)
            if m is None:
                continue
            m._register_load_state_dict_pre_hook(_record_loaded, with_module=True)
            if self.freeze_img:
                for p in m.parameters():
                    p.requires_grad_(False)

    def train(self, mode: bool = True) -> "MSSFDetector":
        super().train(mode)
        if self.freeze_img:
            for m in (getattr(self, "img_backbone", None), getattr(self, "img_neck", None)):
                if m is not None:
                    m.eval()
        return self

    @property
    def num_fusion_blocks(self) -> int:
        return int(self.pts_middle_encoder.num_fusion_blocks)

    def extract_img_feat(self, img: Optional[Tensor], input_metas: List[dict]) -> Any:
        if not self.num_fusion_blocks:
            return None
        if img is None:
            raise MSSFError("imgs: the fusion blocks need the camera image, but the batch has none; load it in the "
                            "pipeline (LoadImageFromFile) and pack it (Pack3DDetInputs keys=[..., 'img'])")
        missing = [i for i, m in enumerate(input_metas) if "lidar2img" not in m]
        if missing:
            raise MSSFError(f"metainfo: samples {missing} have no 'lidar2img'; use infos with calibration and keep "
                            "'lidar2img' in Pack3DDetInputs' meta_keys")
        if self.freeze_img:
            with torch.no_grad():
                feats = super().extract_img_feat(img, input_metas)
        else:
            feats = super().extract_img_feat(img, input_metas)
        return feats

    def extract_pts_feat(self, voxel_dict: Optional[Dict[str, Tensor]], points: Optional[List[Tensor]] = None,
                         img_feats: Optional[Sequence[Tensor]] = None,
                         batch_input_metas: Optional[List[dict]] = None) -> Sequence[Tensor]:
        if points is None:
            raise MSSFError("points: the batch has no 'points' (Pack3DDetInputs keys=['points', ...])")
        cin = int(self.pts_middle_encoder.in_channels)
        bad = [(i, tuple(p.shape)) for i, p in enumerate(points) if p.dim() != 2 or p.shape[1] != cin]
        if bad:
            raise MSSFError(f"points: expected (P, {cin}) per sample (pts_middle_encoder.in_channels; the pipeline's "
                            f"LoadPointsFromFile use_dim), got {bad[:3]}")
        fusion = dict(points=points, img_features=img_feats, batch_input_metas=batch_input_metas) \
            if self.num_fusion_blocks else {}
        if self._consumes_points:
            x = self.pts_middle_encoder(points, img_features=img_feats, batch_input_metas=batch_input_metas) \
                if fusion else self.pts_middle_encoder(points)
        else:
            if voxel_dict is None:
                raise MSSFError("voxels: MSSFSparseEncoder needs voxels; set Det3DDataPreprocessor(voxel=True, voxel_layer=...)")
            voxel_features = self.pts_voxel_encoder(voxel_dict["voxels"], voxel_dict["num_points"], voxel_dict["coors"],
                                                    img_feats, batch_input_metas)
            batch_size = int(voxel_dict["coors"][-1, 0]) + 1
            x = self.pts_middle_encoder(voxel_features, voxel_dict["coors"], batch_size, **fusion)
        self._encoder_ran = True
        if self.with_pts_backbone:
            x = self.pts_backbone(x)
        if self.with_pts_neck:
            x = self.pts_neck(x)
        return x

    def loss(self, batch_inputs_dict: Dict[str, Any], batch_data_samples: List[Any], **kwargs: Any) -> Dict[str, Tensor]:
        if self.num_fusion_blocks:
            check_image_weights(self)  # cheap (names, flags): every step, so a later load_state_dict counts too
        metas = [s.metainfo for s in batch_data_samples]
        self._encoder_ran = False
        img_feats, pts_feats = self.extract_feat(batch_inputs_dict, metas)
        if not self._encoder_ran or not pts_feats:
            raise MSSFError("pts_middle_encoder: not run in this step (no point features); check the model config")
        losses = dict(self.pts_bbox_head.loss(pts_feats, batch_data_samples, **kwargs))
        enc = self.pts_middle_encoder
        if self.num_fusion_blocks and getattr(enc, "last_output", None) is not None:
            gt = [s.gt_instances_3d.bboxes_3d for s in batch_data_samples]
            losses["loss_seg"] = enc.seg_loss(batch_inputs_dict["points"], gt) * self.seg_loss_weight
        if not losses:
            raise MSSFError("loss: the box head returned no losses")
        return losses
