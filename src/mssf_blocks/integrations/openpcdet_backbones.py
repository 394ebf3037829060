"""MSSF fusion backbones with OpenPCDet's ``backbones_3d`` contract, named in a YAML model config.

Register them in ``pcdet/models/backbones_3d/__init__.py`` (two lines)::

    from mssf_blocks.integrations.openpcdet_backbones import OPENPCDET_BACKBONES
    __all__.update(OPENPCDET_BACKBONES)

and name one in the model config (``BACKBONE_3D.NAME``), with the fusion settings beside it::

    BACKBONE_3D:
        NAME: MSSFVoxelResBackBone8x
        NUM_FUSION_BLOCKS: 2        # the first n stages fuse the image (0: radar-only baseline)
        FUSION: msdff               # or sff
        IMAGE_CHANNELS: [64, 64, 64, 64]
        MSDFF_HEADS: 8
        MSDFF_POINTS: 4
        SEG_HIDDEN: [256, 256]      # the semantic-guided head; null for none
        IMAGE_FEATURES_KEY: image_fpn
        AUG_ORDER: [random_world_flip, random_world_rotation, random_world_scaling]

``forward(batch_dict)`` reads ``voxel_features`` / ``voxel_coords`` / ``batch_size`` (from a VFE such
as ``MeanVFE``), builds the camera inputs with
:func:`~mssf_blocks.integrations.openpcdet.fusion_inputs_from_batch_dict` and writes what OpenPCDet's
``VoxelBackBone8x`` / ``VoxelResBackBone8x`` write: ``encoded_spconv_tensor`` (``conv_out``, for
``HeightCompression``), ``encoded_spconv_tensor_stride`` (8), ``multi_scale_3d_features``
(``x_conv1..4``) and ``multi_scale_3d_strides``; with a semantic head also ``mssf_seg_logits``, and
:meth:`get_loss` gives its focal loss from ``gt_boxes``.
"""

from __future__ import annotations

from typing import Any, Dict, Mapping, Tuple

from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations import _backbones
from mssf_blocks.integrations._common import points_with_batch
from mssf_blocks.integrations.openpcdet import DEFAULT_AUGMENTOR_ORDER, fusion_inputs_from_batch_dict

__all__ = ["MSSFVoxelBackBone8x", "MSSFVoxelResBackBone8x", "MSSFVoxelResBackBone8xVoxelNeXt", "OPENPCDET_BACKBONES",
           "settings_from_model_cfg"]

_CFG = {
    "NUM_FUSION_BLOCKS": "num_fusion_blocks", "FUSION": "fusion", "FUSION_POSITION": "fusion_position",
    "IMAGE_CHANNELS": "image_channels", "MSDFF_HEADS": "msdff_heads", "MSDFF_POINTS": "msdff_points",
    "MSDFF_VALUE_PROJECTION": "msdff_value_projection", "MSDFF_VALUE_DIM": "msdff_value_dim",
    "SEG_HIDDEN": "seg_hidden", "CHANNELS": "channels",
    "OUT_CHANNELS": "out_channels",
}
_ADAPTER_CFG = ("IMAGE_FEATURES_KEY", "AUG_ORDER")


def settings_from_model_cfg(model_cfg: Any) -> Tuple[Dict[str, Any], Dict[str, Any]]:
    """``(backbone kwargs, adapter kwargs)`` from a ``BACKBONE_3D`` dict / EasyDict.

    Raises:
        MSSFError: an unknown key (a typo would otherwise silently fall back to a default).
    """
    if not isinstance(model_cfg, Mapping):
        raise MSSFError(f"model_cfg: expected the BACKBONE_3D dict/EasyDict, got {type(model_cfg).__name__}")
    unknown = sorted(k for k in model_cfg if k not in _CFG and k not in _ADAPTER_CFG and k != "NAME")
    if unknown:
        raise MSSFError(f"model_cfg: unknown keys {unknown}; expected among {sorted(_CFG) + list(_ADAPTER_CFG)}")
    kwargs = {_CFG[k]: model_cfg[k] for k in _CFG if k in model_cfg}
    order = model_cfg.get("AUG_ORDER", None)
    adapter = {"image_features_key": model_cfg.get("IMAGE_FEATURES_KEY", "image_fpn"),
               "order": DEFAULT_AUGMENTOR_ORDER if order is None else tuple(order)}
    return kwargs, adapter


class _OpenPCDetFusionBackbone(nn.Module):
    LAYOUT = ""
    LAYOUT_KWARGS: Dict[str, Any] = {}  # what the layout fixes (not a config setting)
    _run = staticmethod(_backbones.run_dense_layout)

    def __init__(self, model_cfg: Any, input_channels: int, grid_size: Any, voxel_size: Any = None,
                 point_cloud_range: Any = None, **kwargs: Any) -> None:
        super().__init__()
        if voxel_size is None or point_cloud_range is None:
            raise MSSFError(
                "voxel_size, point_cloud_range: required (OpenPCDet's build_backbone_3d passes them); got None"
            )
        self.model_cfg = model_cfg
        settings, self.adapter_kwargs = settings_from_model_cfg(model_cfg)
        self.net = _backbones.build(self.LAYOUT, input_channels, point_cloud_range, voxel_size, grid_size,
                                    **settings, **self.LAYOUT_KWARGS)
        self.sparse_shape = list(self.net.input_shape)  # (nz + 1, ny, nx), as OpenPCDet pads z
        self.num_point_features = list(self.net.conv_out)[0].out_channels
        self.backbone_channels = {f"x_conv{i + 1}": c for i, c in enumerate(self.net.channels[:4])}

    @property
    def num_fusion_blocks(self) -> int:
        return self.net.num_fusion_blocks

    def forward(self, batch_dict: Dict[str, Any]) -> Dict[str, Any]:
        inputs = fusion_inputs_from_batch_dict(batch_dict, **self.adapter_kwargs) if self.num_fusion_blocks else None
        out, encoded = self._run(
            self.net, batch_dict["voxel_features"], batch_dict["voxel_coords"], batch_dict["batch_size"], inputs
        )
        batch_dict.update({
            "encoded_spconv_tensor": encoded,
            "encoded_spconv_tensor_stride": 8,
            "multi_scale_3d_features": _backbones.stage_spconv(out),
            "multi_scale_3d_strides": {f"x_conv{i + 1}": s[-1] for i, s in enumerate(self.net.strides[:4])},
        })
        if out.seg_logits is not None:
            batch_dict["mssf_seg_logits"] = out.seg_logits
            batch_dict["_mssf_backbone_output"] = out
        return batch_dict

    def get_loss(self, batch_dict: Mapping[str, Any]) -> Tuple[Tensor, Dict[str, float]]:
        """``(loss_seg, tb_dict)``: the semantic head's focal loss (add it in ``get_training_loss``).

        Labels come from ``batch_dict['gt_boxes']`` ``(B, G, 7 + 1)`` (zero-padded rows are dropped),
        in the same augmented frame as the points.
        """
        out = batch_dict.get("_mssf_backbone_output")
        if out is None:
            raise MSSFError("batch_dict: no semantic-head output; set SEG_HIDDEN and NUM_FUSION_BLOCKS > 0")
        if "gt_boxes" not in batch_dict:
            raise MSSFError("batch_dict: expected 'gt_boxes' (B, G, 8) for the semantic-head loss")
        points, points_batch = points_with_batch(batch_dict["points"], "batch_dict['points']")
        gt = batch_dict["gt_boxes"]
        boxes = [g[(g[:, 3:6] > 0).all(1), :7] for g in gt]  # collate_batch pads with all-zero rows
        loss = _backbones.seg_loss(self.net, out, points, points_batch, boxes)
        return loss, {"loss_mssf_seg": float(loss.detach())}


class MSSFVoxelBackBone8x(_OpenPCDetFusionBackbone):
    """OpenPCDet's ``VoxelBackBone8x`` (SECOND) layout with MSSF fusion in the first stages."""

    LAYOUT = "VoxelBackBone8x"


class MSSFVoxelResBackBone8x(_OpenPCDetFusionBackbone):
    """OpenPCDet's ``VoxelResBackBone8x`` (CenterPoint / PV-RCNN++) layout with MSSF fusion."""

    LAYOUT = "VoxelResBackBone8x"


class MSSFVoxelResBackBone8xVoxelNeXt(_OpenPCDetFusionBackbone):
    """OpenPCDet's ``VoxelResBackBone8xVoxelNeXt`` layout (the paper's MSSF-V) with MSSF fusion.

    Six residual stages (default: the paper's doubled widths, ``CHANNELS: [32, 32, 64, 128, 256, 256,
    256]`` = stem, stages 1-6), stages 4-6 merged into a sparse BEV at stride 8 and a 3 x 3 submanifold
    ``conv_out`` and ``shared_conv`` as OpenPCDet's (``OUT_CHANNELS``, default 256; the grid padded by one z
    layer). ``encoded_spconv_tensor`` is that 2D sparse tensor (indices ``(b, y, x)``), what
    ``VoxelNeXtHead`` reads (``DENSE_HEAD.INPUT_FEATURES`` = ``OUT_CHANNELS``).
    """

    LAYOUT = "VoxelResBackBone8xVoxelNeXt"
    LAYOUT_KWARGS = {"z_pad": 1}  # OpenPCDet's sparse_shape = grid_size[::-1] + [1, 0, 0]
    _run = staticmethod(_backbones.run_voxelnext_layout)

    def __init__(self, model_cfg: Any, input_channels: int, grid_size: Any, voxel_size: Any = None,
                 point_cloud_range: Any = None, **kwargs: Any) -> None:
        super().__init__(model_cfg, input_channels, grid_size, voxel_size, point_cloud_range, **kwargs)
        _backbones.openpcdet_voxelnext_tail(self.net)  # OpenPCDet's conv_out + shared_conv (the example's replaced)


#: what to merge into ``pcdet.models.backbones_3d.__all__``
OPENPCDET_BACKBONES = {"MSSFVoxelBackBone8x": MSSFVoxelBackBone8x, "MSSFVoxelResBackBone8x": MSSFVoxelResBackBone8x,
                       "MSSFVoxelResBackBone8xVoxelNeXt": MSSFVoxelResBackBone8xVoxelNeXt}
