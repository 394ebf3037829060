"""The MSSF pillar fusion stages of an OpenPCDet backbone on a BEV grid (MSSF-PP, VoxelNeXt-2D).

Paper Sec. III "Extend to Pillar": in each of the first ``NUM_FUSION_BLOCKS`` stages of a pillar network
the BEV features are lifted into the radar points' voxels on the stage's x/y cells (``BEV(x, y) +
HeightEmb(z)``, ``LIFT_Z_SIZE`` in z), fused with the image (MSDFF / SFF) and summed back per ``(x, y)``;
the last stage carries the semantic-guided head. Each step is one :class:`~mssf_blocks.PillarFusionStage`
(``merge="replace"``). :class:`PillarFusionStages` holds them and what they share (the settings read from the
model config, the lift grid, the camera inputs' adapter settings, the semantic loss); a backbone mixes it in
and calls :meth:`PillarFusionStages.fuse` on its maps. Importing this module imports no OpenPCDet.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations._common import points_with_batch
from mssf_blocks.integrations.openpcdet import DEFAULT_AUGMENTOR_ORDER

__all__ = ["FUSION_DEFAULTS", "PillarFusionStages"]

#: the fusion keys of the model config and their defaults
FUSION_DEFAULTS: dict[str, Any] = {
    "NUM_FUSION_BLOCKS": 0, "FUSION": "msdff", "FUSION_POSITION": "before_residual", "LIFT_Z_SIZE": 0.125,
    "IMAGE_CHANNELS": None, "MSDFF_HEADS": 8, "MSDFF_POINTS": 4, "MSDFF_VALUE_PROJECTION": "after_sampling",
    "MSDFF_VALUE_DIM": None, "SEG_HIDDEN": [256, 256], "IMAGE_FEATURES_KEY": "image_fpn", "AUG_ORDER": None,
}


class PillarFusionStages:
    """Mixin of an ``nn.Module`` backbone: the fusion settings, the stages (``self.stages``) and the seg loss."""

    def init_fusion(self, model_cfg: Mapping, key: str, stock_keys: Sequence[str], channels: Sequence[int],
                    strides: Sequence[int], voxel_size: Any, point_cloud_range: Any) -> None:
        """Read the fusion keys of ``model_cfg`` (``MODEL.<key>``) and build the stages.

        Args:
            stock_keys: the keys the framework's own backbone reads (any other unknown key is refused).
            channels, strides: ``C`` and the x/y stride (to the pillar grid) of every stage that may fuse.
        """
        if not isinstance(model_cfg, Mapping):
            raise MSSFError(f"MODEL.{key}: expected a dict/EasyDict, got {type(model_cfg).__name__}")
        unknown = sorted(k for k in model_cfg if k not in stock_keys and k not in FUSION_DEFAULTS and k != "NAME")
        if unknown:
            raise MSSFError(f"MODEL.{key}: unknown keys {unknown}; expected among "
                            f"{sorted(set(stock_keys) | set(FUSION_DEFAULTS))}")
        s = {k: model_cfg.get(k, d) for k, d in FUSION_DEFAULTS.items()}
        n = s["NUM_FUSION_BLOCKS"]
        if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= len(channels):
            raise MSSFError(f"MODEL.{key}.NUM_FUSION_BLOCKS: expected an int in [0, {len(channels)}] (the backbone's "
                            f"stages), got {n!r}")
        if s["FUSION_POSITION"] not in ("before_residual", "after_residual"):
            raise MSSFError(f"MODEL.{key}.FUSION_POSITION: expected 'before_residual' or 'after_residual', "
                            f"got {s['FUSION_POSITION']!r}")
        self.num_fusion_blocks, self.fusion_position = n, s["FUSION_POSITION"]
        order = s["AUG_ORDER"]
        self.adapter_kwargs = {"image_features_key": s["IMAGE_FEATURES_KEY"],
                               "order": DEFAULT_AUGMENTOR_ORDER if order is None else tuple(order)}
        self.stages = nn.ModuleList()
        self.fusion_strides = [int(st) for st in strides[:n]]
        if n:
            self._build_stages(s, key, [int(c) for c in channels[:n]], voxel_size, point_cloud_range)

    def _build_stages(self, s: dict[str, Any], key: str, channels: list, voxel_size: Any, point_cloud_range: Any) -> None:
        from mssf_blocks.blocks import FusionBlock, PillarFusionStage
        from mssf_blocks.heads import SemanticGuidedHead
        from mssf_blocks.lift import PillarLift
        from mssf_blocks.samplers import QueryInit
        from mssf_blocks.voxel_grid import VoxelGrid

        from ..models.backbones.fusion_stage import _make_fusion

        if voxel_size is None or point_cloud_range is None:
            raise MSSFError("voxel_size, point_cloud_range: required for the fusion blocks (the MSSF detectors pass "
                            "OpenPCDet's); got None")
        if not s["IMAGE_CHANNELS"]:
            raise MSSFError(f"MODEL.{key}.IMAGE_CHANNELS: required (one entry per image level) when "
                            f"NUM_FUSION_BLOCKS > 0, got {s['IMAGE_CHANNELS']!r}")
        if s["FUSION"] not in ("msdff", "sff"):
            raise MSSFError(f"MODEL.{key}.FUSION: expected 'msdff' or 'sff', got {s['FUSION']!r}")
        pcr = tuple(float(v) for v in point_cloud_range)
        vx, vy, vz = (float(v) for v in voxel_size)
        if abs((pcr[5] - pcr[2]) - vz) > 1e-6:
            raise MSSFError(f"DATA_CONFIG.DATA_PROCESSOR transform_points_to_voxels VOXEL_SIZE: a pillar spans the "
                            f"whole z range {pcr[5] - pcr[2]:g} m (POINT_CLOUD_RANGE), got z size {vz:g}")
        self.lift_grid = VoxelGrid(voxel_size=(vx, vy, float(s["LIFT_Z_SIZE"])), point_cloud_range=pcr)
        image_channels = [int(c) for c in s["IMAGE_CHANNELS"]]
        seg_hidden = s["SEG_HIDDEN"]
        for i, c in enumerate(channels):
            query_init = QueryInit(c, image_channels[0], c, pcr) if s["FUSION"] == "msdff" and i == 0 else None
            last = i == len(channels) - 1
            head = SemanticGuidedHead(c, hidden=tuple(int(h) for h in seg_hidden)) if last and seg_hidden else None
            fusion = _make_fusion(s["FUSION"], c, image_channels, int(s["MSDFF_HEADS"]), int(s["MSDFF_POINTS"]),
                                  s["MSDFF_VALUE_PROJECTION"], s["MSDFF_VALUE_DIM"])
            block = FusionBlock(fusion, query_init=query_init, semantic_head=head)
            # the lift voxels are coarsened to the map's x/y cells (lift_voxels), hence stride 1
            self.stages.append(PillarFusionStage(PillarLift(c, self.lift_grid.spatial_shape[0], stride=1), block))

    def lift_voxels(self, batch_dict: Mapping[str, Any]) -> list:
        """The radar points' voxels (pillar x/y cells, ``LIFT_Z_SIZE`` in z) at each fusion stage's stride."""
        from mssf_blocks.sparse_voxels import SparseVoxels

        from ..models.backbones.pillars import PointPillarsBackbone
        from ..models.voxelize import dynamic_voxelize

        points, batch = points_with_batch(batch_dict["points"], "batch_dict['points']")
        b = int(batch_dict["batch_size"])
        vox = dynamic_voxelize(points[:, :3], batch, b, self.lift_grid)
        v = SparseVoxels(vox.features[:, :1], vox.coords, batch_size=b, grid=self.lift_grid)
        return [PointPillarsBackbone._coarsen(v, s) for s in self.fusion_strides]

    def fuse(self, i: int, bev: Tensor, voxels: Any, inputs: Any, batch_dict: dict[str, Any]) -> Tensor:
        """Stage ``i`` on a dense ``(B, C, H_i, W_i)`` map; the last stage's head output goes into ``batch_dict``."""
        stage = self.stages[i]
        if stage.block.semantic_head is None:
            return stage(bev, voxels, inputs)
        out = stage(bev, voxels, inputs, return_logits=True)
        batch_dict["mssf_seg_logits"] = out.logits
        batch_dict["_mssf_seg_output"] = out
        return out[0]

    def get_loss(self, batch_dict: Mapping[str, Any]) -> tuple[Tensor, dict[str, float]]:
        """``(loss_seg, tb_dict)``: the semantic head's focal loss on the centroids the last fusion stage
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
