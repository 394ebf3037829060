"""What every MSSF example backbone shares: the fusion-block builder, its checks and the output type.

The first ``num_fusion_blocks`` stages of a backbone are :class:`mssf_blocks.blocks.FusionBlock` s whose
fusion module (SFF or MSDFF) is built here; every backbone returns a :class:`BackboneOutput`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Union

from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse_voxels import SparseVoxels

__all__ = ["BackboneOutput", "FUSION_TYPES", "FUSION_POSITIONS"]

FUSION_TYPES = ("msdff", "sff")


FUSION_POSITIONS = ("before_residual", "after_residual")

@dataclass
class BackboneOutput:
    """What a backbone hands to the neck/head.

    Attributes:
        stages: :class:`SparseVoxels` output of every stage (for pillars: the fused voxels of the fusion
            blocks only).
        bev: dense ``(B, C, H, W)`` BEV map (SECOND, CenterPoint, PointPillars) or ``None``.
        sparse_bev: ``(features (M, C), coords (M, 3) (b, y, x) int32)`` (VoxelNeXt) or ``None``.
        seg_logits: ``(N_s,)`` semantic-head logits of the voxels after the last fusion block, or ``None``.
        seg_voxels: those voxels (for their centroids in the loss), or ``None``.
    """

    stages: List[SparseVoxels]
    bev: Optional[Tensor] = None
    sparse_bev: Optional[Tuple[Tensor, Tensor]] = None
    seg_logits: Optional[Tensor] = None
    seg_voxels: Optional[SparseVoxels] = None


def _check_fusion_args(num_fusion_blocks: int, max_blocks: int, fusion: str, fusion_position: str) -> None:
    if isinstance(num_fusion_blocks, bool) or not isinstance(num_fusion_blocks, int) or not 0 <= num_fusion_blocks <= max_blocks:
        raise MSSFError(f"num_fusion_blocks: expected an int in [0, {max_blocks}], got {num_fusion_blocks!r}")
    if fusion not in FUSION_TYPES:
        raise MSSFError(f"fusion: expected one of {FUSION_TYPES}, got {fusion!r}")
    if fusion_position not in FUSION_POSITIONS:
        raise MSSFError(f"fusion_position: expected one of {FUSION_POSITIONS}, got {fusion_position!r}")


def _make_fusion(kind: str, channels: int, image_channels: Sequence[int], msdff_heads: int, msdff_points: int,
                 value_projection: str = "after_sampling", value_dim: Union[int, str, None] = None,
                 authors_switches: bool = False):
    from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES
    from mssf_blocks.samplers import MSDFF, SFF

    if kind == "sff":
        return SFF(list(image_channels), channels, **(OFFICIAL_SWITCHES["sff"] if authors_switches else {}))
    if value_dim == "voxel_channels":  # the narrow layout: the image projected to the voxel width first
        value_dim = channels
    elif value_dim is not None and (isinstance(value_dim, bool) or not isinstance(value_dim, int)):
        raise MSSFError(f"msdff_value_dim: expected None, an int or 'voxel_channels', got {value_dim!r}")
    return MSDFF(list(image_channels), channels, value_dim, num_heads=msdff_heads, num_levels=len(image_channels),
                 num_points=msdff_points, value_projection=value_projection,
                 **(OFFICIAL_SWITCHES["msdff"] if authors_switches else {}))

