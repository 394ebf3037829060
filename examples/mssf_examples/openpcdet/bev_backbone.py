"""MSSF-PP's 2D backbone for OpenPCDet (``BACKBONE_2D.NAME: MSSFBaseBEVBackbone``).

The paper's pillar version (Sec. III "Extend to Pillar") replaces the first ``n`` blocks of the BEV
backbone with fusion blocks: after block ``i``'s strided convolution (``FUSION_POSITION:
before_residual``, the default, as ``mssf_blocks.integrations.mmdet3d_pillars.MSSFPillarEncoder``) or
after its convolutions (``after_residual``) the map is lifted into the radar points' voxels at the map's
x/y resolution (``BEV(x, y) + HeightEmb(z)``), fused with the image (MSDFF / SFF) and summed back per
``(x, y)``; the last fusion block carries the semantic-guided head. Each of those steps is one
:class:`~mssf_blocks.PillarFusionStage` (``merge="replace"``). The fusion therefore sits *inside* the
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

from collections.abc import Mapping
from typing import Any

import torch
from pcdet.models.backbones_2d.base_bev_backbone import BaseBEVBackbone
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations._common import points_with_batch
from mssf_blocks.integrations.openpcdet import DEFAULT_AUGMENTOR_ORDER, fusion_inputs_from_batch_dict

__all__ = ["OPENPCDET_BEV_BACKBONES", "MSSFBaseBEVBackbone"]

#: BaseBEVBackbone's own keys (read by its constructor)
_STOCK_KEYS = ("NAME", "LAYER_NUMS", "LAYER_STRIDES", "NUM_FILTERS", "UPSAMPLE_STRIDES", "NUM_UPSAMPLE_FILTERS",
               "USE_CONV_FOR_NO_STRIDE")
#: the fusion keys and their defaults
_FUSION_DEFAULTS: dict[str, Any] = {
    "NUM_FUSION_BLOCKS": 0, "FUSION": "msdff", "FUSION_POSITION": "before_residual", "LIFT_Z_SIZE": 0.125,
    "IMAGE_CHANNELS": None, "MSDFF_HEADS": 8, "MSDFF_POINTS": 4, "MSDFF_VALUE_PROJECTION": "after_sampling",
    "MSDFF_VALUE_DIM": None, "SEG_HIDDEN": [256, 256], "IMAGE_FEATURES_KEY": "image_fpn", "AUG_ORDER": None,
}
#: the layers of a BaseBEVBackbone block up to its strided convolution's ReLU (ZeroPad2d, Conv2d, BN, ReLU)
_DOWNSAMPLE_LAYERS = 4


class MSSFBaseBEVBackbone(BaseBEVBackbone):
    """OpenPCDet's ``BaseBEVBackbone`` with MSSF fusion stages in its first ``NUM_FUSION_BLOCKS`` blocks.

    ``forward(batch_dict)`` reads ``spatial_features (B, C, H, W)`` (``PointPillarScatter``), ``points``
    and, when it fuses, the camera keys and the image levels (``IMAGE_FEATURES_KEY``); it writes what
    ``BaseBEVBackbone`` writes (``spatial_features_2d``, and the same values), plus ``mssf_seg_logits`` with
    the semantic head. :meth:`get_loss` gives the head's focal loss from ``gt_boxes``.
    """

    def __init__(self, model_cfg: Any, input_channels: int, voxel_size: Any = None, point_cloud_range: Any = None,
                 **kwargs: Any) -> None:
        if not isinstance(model_cfg, Mapping):
            raise MSSFError(f"MODEL.BACKBONE_2D: expected a dict/EasyDict, got {type(model_cfg).__name__}")
        unknown = sorted(k for k in model_cfg if k not in _STOCK_KEYS and k not in _FUSION_DEFAULTS)
        if unknown:
            raise MSSFError(f"MODEL.BACKBONE_2D: unknown keys {unknown}; expected among "
                            f"{sorted(_STOCK_KEYS + tuple(_FUSION_DEFAULTS))}")
        super().__init__(model_cfg, input_channels)
        s = {k: model_cfg.get(k, d) for k, d in _FUSION_DEFAULTS.items()}
        n = s["NUM_FUSION_BLOCKS"]
        if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= len(self.blocks):
            raise MSSFError(f"MODEL.BACKBONE_2D.NUM_FUSION_BLOCKS: expected an int in [0, {len(self.blocks)}] "
                            f"(LAYER_NUMS has {len(self.blocks)} blocks), got {n!r}")
        if s["FUSION_POSITION"] not in ("before_residual", "after_residual"):
            raise MSSFError(f"MODEL.BACKBONE_2D.FUSION_POSITION: expected 'before_residual' or 'after_residual', "
                            f"got {s['FUSION_POSITION']!r}")
        self.num_fusion_blocks, self.fusion_position = n, s["FUSION_POSITION"]
        order = s["AUG_ORDER"]
        self.adapter_kwargs = {"image_features_key": s["IMAGE_FEATURES_KEY"],
                               "order": DEFAULT_AUGMENTOR_ORDER if order is None else tuple(order)}
        self.stages = nn.ModuleList()
        if n:
            self._build_stages(s, input_channels, voxel_size, point_cloud_range)

    def _build_stages(self, s: dict[str, Any], input_channels: int, voxel_size: Any, point_cloud_range: Any) -> None:
        from mssf_blocks.blocks import FusionBlock, PillarFusionStage
        from mssf_blocks.heads import SemanticGuidedHead
        from mssf_blocks.lift import PillarLift
        from mssf_blocks.samplers import QueryInit
        from mssf_blocks.voxel_grid import VoxelGrid

        from ..models.backbones.fusion_stage import _make_fusion

        if voxel_size is None or point_cloud_range is None:
            raise MSSFError("voxel_size, point_cloud_range: required for the fusion blocks (MSSFPointPillar's "
                            "build_backbone_2d passes OpenPCDet's); got None")
        if not s["IMAGE_CHANNELS"]:
            raise MSSFError("MODEL.BACKBONE_2D.IMAGE_CHANNELS: required (one entry per image level) when "
                            f"NUM_FUSION_BLOCKS > 0, got {s['IMAGE_CHANNELS']!r}")
        if s["FUSION"] not in ("msdff", "sff"):
            raise MSSFError(f"MODEL.BACKBONE_2D.FUSION: expected 'msdff' or 'sff', got {s['FUSION']!r}")
        pcr = tuple(float(v) for v in point_cloud_range)
        vx, vy, vz = (float(v) for v in voxel_size)
        if abs((pcr[5] - pcr[2]) - vz) > 1e-6:
            raise MSSFError(f"DATA_CONFIG.DATA_PROCESSOR transform_points_to_voxels VOXEL_SIZE: a pillar spans the "
                            f"whole z range {pcr[5] - pcr[2]:g} m (POINT_CLOUD_RANGE), got z size {vz:g}")
        self.lift_grid = VoxelGrid(voxel_size=(vx, vy, float(s["LIFT_Z_SIZE"])), point_cloud_range=pcr)
        image_channels = [int(c) for c in s["IMAGE_CHANNELS"]]
        seg_hidden = s["SEG_HIDDEN"]
        strides, stride = [], 1
        for i in range(self.num_fusion_blocks):
            stride *= int(self.model_cfg.LAYER_STRIDES[i])
            strides.append(stride)
            c = int(self.model_cfg.NUM_FILTERS[i])
            query_init = QueryInit(c, image_channels[0], c, pcr) if s["FUSION"] == "msdff" and i == 0 else None
            last = i == self.num_fusion_blocks - 1
            head = SemanticGuidedHead(c, hidden=tuple(int(h) for h in seg_hidden)) if last and seg_hidden else None
            fusion = _make_fusion(s["FUSION"], c, image_channels, int(s["MSDFF_HEADS"]), int(s["MSDFF_POINTS"]),
                                  s["MSDFF_VALUE_PROJECTION"], s["MSDFF_VALUE_DIM"])
            block = FusionBlock(fusion, query_init=query_init, semantic_head=head)
            # the lift voxels are coarsened to the map's x/y cells (lift_voxels), hence stride 1
            self.stages.append(PillarFusionStage(PillarLift(c, self.lift_grid.spatial_shape[0], stride=1), block))
        self.fusion_strides = strides

    def lift_voxels(self, batch_dict: Mapping[str, Any]) -> list:
        """The radar points' voxels (pillar x/y cells, ``LIFT_Z_SIZE`` in z) at each fusion block's stride."""
        from mssf_blocks.sparse_voxels import SparseVoxels

        from ..models.backbones.pillars import PointPillarsBackbone
        from ..models.voxelize import dynamic_voxelize

        points, batch = points_with_batch(batch_dict["points"], "batch_dict['points']")
        b = int(batch_dict["batch_size"])
        vox = dynamic_voxelize(points[:, :3], batch, b, self.lift_grid)
        v = SparseVoxels(vox.features[:, :1], vox.coords, batch_size=b, grid=self.lift_grid)
        return [PointPillarsBackbone._coarsen(v, s) for s in self.fusion_strides]

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
                x = self._fuse(i, x, lifts[i], inputs, data_dict)
                x = block[split:](x)
            else:
                x = block(x)
            ups.append(self.deblocks[i](x) if len(self.deblocks) > 0 else x)
        x = ups[0] if len(ups) == 1 else torch.cat(ups, dim=1)
        if len(self.deblocks) > len(self.blocks):
            x = self.deblocks[-1](x)
        data_dict["spatial_features_2d"] = x
        return data_dict

    def _fuse(self, i: int, bev: Tensor, voxels: Any, inputs: Any, data_dict: dict[str, Any]) -> Tensor:
        stage = self.stages[i]
        if stage.block.semantic_head is None:
            return stage(bev, voxels, inputs)
        out = stage(bev, voxels, inputs, return_logits=True)
        data_dict["mssf_seg_logits"] = out.logits
        data_dict["_mssf_seg_output"] = out
        return out[0]

    def get_loss(self, batch_dict: Mapping[str, Any]) -> tuple[Tensor, dict[str, float]]:
        """``(loss_seg, tb_dict)``: the semantic head's focal loss on the centroids the last fusion block
        projected, labels from ``batch_dict['gt_boxes']`` ``(B, G, 7 + 1)`` (zero rows dropped)."""
        out = batch_dict.get("_mssf_seg_output")
        if out is None:
            raise MSSFError("batch_dict: no semantic-head output; set SEG_HIDDEN and NUM_FUSION_BLOCKS > 0")
        if "gt_boxes" not in batch_dict:
            raise MSSFError("batch_dict: expected 'gt_boxes' (B, G, 8) for the semantic-head loss")
        boxes = [g[(g[:, 3:6] > 0).all(1), :7] for g in batch_dict["gt_boxes"]]  # collate_batch pads with zeros
        head = self.stages[self.num_fusion_blocks - 1].block.semantic_head
        loss = head.loss_from_boxes(out.logits, out.centroids.to(out.logits.dtype), out.batch_index,
                                    [g.to(out.centroids) for g in boxes])
        return loss, {"loss_mssf_seg": float(loss.detach())}


#: what to merge into ``pcdet.models.backbones_2d.__all__``
OPENPCDET_BEV_BACKBONES = {"MSSFBaseBEVBackbone": MSSFBaseBEVBackbone}
