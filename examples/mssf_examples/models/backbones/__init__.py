"""Voxel and pillar backbones with MSSF fusion blocks (real sparse convolution with spconv).

Sparse 3D backbones (spconv ``SubMConv3d`` / ``SparseConv3d``), laid out as in OpenPCDet:

* :class:`SECONDBackbone` — ``VoxelBackBone8x`` (SECOND, Yan et al. 2018): plain submanifold convs.
* :class:`CenterPointBackbone` — ``VoxelResBackBone8x`` (CenterPoint, Yin et al. 2021): residual blocks.
* :class:`VoxelNeXtBackbone` — VoxelNeXt (Chen et al. 2023): six residual stages with the paper's
  doubled channels; stages 4-6 are merged into a sparse BEV by summing equal ``(b, y, x)``
  (:func:`merge_sparse_bev`).
* :class:`PointPillarsBackbone` — PointPillars (Lang et al. 2019): pillar feature net, dense 2D blocks;
  a fusion block lifts the BEV into the radar voxels with :class:`mssf_blocks.lift.PillarLift`, fuses
  them with the image and sums them back (paper Sec. "Extend to Pillar").

The first ``num_fusion_blocks`` stages are :class:`mssf_blocks.blocks.FusionBlock` s (SFF or MSDFF,
fusion before or after the residual blocks); a :class:`mssf_blocks.heads.SemanticGuidedHead` follows
the last fusion block. ``num_fusion_blocks=0`` is the radar-only baseline.

Modules by concept: :mod:`.fusion_stage` (what every backbone shares: the fusion-block builder, its
argument checks, :class:`BackboneOutput`), :mod:`.voxel` (the spconv building blocks,
:class:`SparseFusionBackbone`, SECOND, CenterPoint), :mod:`.voxelnext` (VoxelNeXt and its sparse BEV
merge) and :mod:`.pillars` (PointPillars); import the names from here.
"""

from .fusion_stage import FUSION_POSITIONS, FUSION_TYPES, BackboneOutput
from .pillars import PointPillarsBackbone
from .pillars_authors import AuthorsPointPillarsBackbone
from .voxel import CenterPointBackbone, SECONDBackbone, SparseBasicBlock, SparseFusionBackbone
from .voxelnext import VoxelNeXtBackbone, merge_sparse_bev, merge_sparse_bev_dense_reference

__all__ = [
    "BackboneOutput",
    "SparseBasicBlock",
    "SparseFusionBackbone",
    "SECONDBackbone",
    "CenterPointBackbone",
    "VoxelNeXtBackbone",
    "PointPillarsBackbone",
    "AuthorsPointPillarsBackbone",
    "merge_sparse_bev",
    "merge_sparse_bev_dense_reference",
    "FUSION_TYPES",
    "FUSION_POSITIONS",
]
