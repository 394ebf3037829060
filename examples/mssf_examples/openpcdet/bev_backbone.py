"""MSSF-PP's 2D backbone for OpenPCDet (``BACKBONE_2D.NAME: MSSFBaseBEVBackbone``).

The paper's pillar version (Sec. III "Extend to Pillar") replaces the first ``n`` blocks of the BEV
backbone with fusion blocks: after block ``i``'s strided convolution (``FUSION_POSITION:
before_residual``, the default, as ``mssf_blocks.integrations.mmdet3d_pillars.MSSFPillarEncoder``) or
after its convolutions (``after_residual``) the map is lifted into the radar points' voxels at the map's
x/y resolution (``BEV(x, y) + HeightEmb(z)``), fused with the image (MSDFF / SFF) and summed back per
``(x, y)``; the last fusion block carries the semantic-guided head
(:class:`~mssf_examples.openpcdet.pillar_fusion.PillarFusionStages`). The fusion therefore sits *inside* the
2D backbone, after ``PointPillarScatter``, not on the pillars before scattering: OpenPCDet's
``PillarVFE`` / ``PointPillarScatter`` / ``AnchorHeadSingle`` stay stock.

Everything else is OpenPCDet's ``BaseBEVBackbone`` (the class is its subclass: the same ``blocks.*`` /
``deblocks.*`` parameters, so a stock PointPillars checkpoint loads and ``NUM_FUSION_BLOCKS: 0`` is the
stock backbone). Model config, beside ``BaseBEVBackbone``'s keys::

    BACKBONE_2D:
        NAME: MSSFBaseBEVBackbone
        LAYER_NUMS: [3, 5, 5]  ...           # BaseBEVBackbone's
        NUM_FUSION_BLOCKS: 2                 # the first n blocks fuse the image (0: radar only)
        FUSION: msdff                        # or sff
        FUSION_POSITION: before_residual
        LIFT_Z_SIZE: 0.125                   # z size (m) of the lift voxels
        IMAGE_CHANNELS: [256, 256, 256, 256]
        MSDFF_HEADS: 8
        MSDFF_POINTS: 4
        SEG_HIDDEN: [256, 256]
        IMAGE_FEATURES_KEY: image_fpn
        AUG_ORDER: [random_world_flip, random_world_rotation, random_world_scaling]

The grid (pillar size, range) is OpenPCDet's: ``MSSFPointPillar.build_backbone_2d`` passes
``voxel_size`` / ``point_cloud_range``. Importing this module imports OpenPCDet.
"""

from __future__ import annotations

from typing import Any

import torch
from pcdet.models.backbones_2d.base_bev_backbone import BaseBEVBackbone

from mssf_blocks.integrations.openpcdet import fusion_inputs_from_batch_dict

from .pillar_fusion import PillarFusionStages

__all__ = ["OPENPCDET_BEV_BACKBONES", "MSSFBaseBEVBackbone"]

#: BaseBEVBackbone's own keys (read by its constructor)
_STOCK_KEYS = ("LAYER_NUMS", "LAYER_STRIDES", "NUM_FILTERS", "UPSAMPLE_STRIDES", "NUM_UPSAMPLE_FILTERS",
               "USE_CONV_FOR_NO_STRIDE")
#: the layers of a BaseBEVBackbone block up to its strided convolution's ReLU (ZeroPad2d, Conv2d, BN, ReLU)
_DOWNSAMPLE_LAYERS = 4


class MSSFBaseBEVBackbone(PillarFusionStages, BaseBEVBackbone):
    """OpenPCDet's ``BaseBEVBackbone`` with MSSF fusion stages in its first ``NUM_FUSION_BLOCKS`` blocks.

    ``forward(batch_dict)`` reads ``spatial_features (B, C, H, W)`` (``PointPillarScatter``), ``points``
    and, when it fuses, the camera keys and the image levels (``IMAGE_FEATURES_KEY``); it writes what
    ``BaseBEVBackbone`` writes (``spatial_features_2d``), plus ``mssf_seg_logits`` with the semantic head.
    :meth:`get_loss` gives the head's focal loss from ``gt_boxes``.
    """

    def __init__(self, model_cfg: Any, input_channels: int, voxel_size: Any = None, point_cloud_range: Any = None,
                 **kwargs: Any) -> None:
        BaseBEVBackbone.__init__(self, model_cfg, input_channels)
        strides, stride = [], 1
        for s in model_cfg.get("LAYER_STRIDES", None) or []:
            stride *= int(s)
            strides.append(stride)
        self.init_fusion(model_cfg, "BACKBONE_2D", _STOCK_KEYS, list(model_cfg.get("NUM_FILTERS", None) or []),
                         strides, voxel_size, point_cloud_range)

    def forward(self, data_dict: dict[str, Any]) -> dict[str, Any]:
        if not self.num_fusion_blocks:
            return super().forward(data_dict)
        inputs = fusion_inputs_from_batch_dict(data_dict, **self.adapter_kwargs)
        lifts = self.lift_voxels(data_dict)
        x, ups = data_dict["spatial_features"], []
        for i, block in enumerate(self.blocks):
            if i < self.num_fusion_blocks:
                split = _DOWNSAMPLE_LAYERS if self.fusion_position == "before_residual" else len(block)
                x = block[:split](x)
                x = self.fuse(i, x, lifts[i], inputs, data_dict)
                x = block[split:](x)
            else:
                x = block(x)
            ups.append(self.deblocks[i](x) if len(self.deblocks) > 0 else x)
        x = ups[0] if len(ups) == 1 else torch.cat(ups, dim=1)
        if len(self.deblocks) > len(self.blocks):
            x = self.deblocks[-1](x)
        data_dict["spatial_features_2d"] = x
        return data_dict


#: what to merge into ``pcdet.models.backbones_2d.__all__``
OPENPCDET_BEV_BACKBONES = {"MSSFBaseBEVBackbone": MSSFBaseBEVBackbone}
