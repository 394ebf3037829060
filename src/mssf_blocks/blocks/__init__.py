"""The blocks a detector swaps in: :class:`FusionBlock` (a sparse-backbone stage with MSSF fusion, paper
Sec. III-C) and :class:`PillarFusionStage` (the pillar version, Sec. III-G)."""

from mssf_blocks.blocks.fusion_block import FusionBlock, FusionBlockOutput, infer_downsample_stride
from mssf_blocks.blocks.pillar_fusion_stage import PillarFusionStage

__all__ = ["FusionBlock", "FusionBlockOutput", "infer_downsample_stride", "PillarFusionStage"]
