"""PointPillars (Lang et al. 2019) with MSSF fusion blocks (paper Sec. "Extend to Pillar").

A fusion block lifts the BEV map into the radar voxels with :class:`mssf_blocks.lift.PillarLift`, fuses
them with the image and sums them back. Import :class:`PointPillarsBackbone` from
:mod:`mssf_examples.models.backbones`.
"""

from __future__ import annotations

from typing import List, Optional, Sequence, Union

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.lift import _add_into_pillars
from mssf_blocks.sparse_voxels import SparseVoxels

from ..voxelize import PillarFeatureNet, VoxelGrid, dynamic_voxelize
from .fusion_stage import BackboneOutput, _check_fusion_args, _make_fusion

__all__ = ["PointPillarsBackbone"]


def replace_occupied_pillars(bev: Tensor, voxels: SparseVoxels, stride=(1, 1)) -> Tensor:
    """``bev (B, C, H_b, W_b)`` with every pillar that ``voxels`` occupy replaced by the sum of their
    features (``(N, C)``; voxel ``(b, z, y, x)`` in pillar ``(b, y // sy, x // sx)``); the other
    pillars keep ``bev``'s features. Differentiable in both.

    The occupied cells of a copy of the map are zeroed and the voxels added into them in voxel order
    (:func:`mssf_blocks.functional.lift._add_into_pillars`, the sums of ``PillarLift.to_bev``, bit for
    bit). Static shapes, so it exports; one pass over the map instead of the five of two dense
    ``to_bev`` maps (sums and occupancy), a comparison and a ``torch.where`` (measured 6 ms a VoD frame
    on one core). The copy is channels-last if the map is, NCHW otherwise.
    """
    sy, sx = stride
    c = voxels.coords.long()
    _, _, hb, wb = bev.shape
    cell = torch.div(c[:, 2], sy, rounding_mode="floor") * wb + torch.div(c[:, 3], sx, rounding_mode="floor")
    layout = torch.channels_last if bev.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format
    fused = bev.to(dtype=torch.promote_types(bev.dtype, voxels.features.dtype), memory_format=layout, copy=True)
    return _add_into_pillars(fused, c[:, 0], cell, voxels.features.to(fused.dtype), clear=True)


class PointPillarsBackbone(nn.Module):
    """PointPillars: PFN, three 2D blocks (strides 2, 2, 2), upsampling and concatenation.

    Fusion block ``i < num_fusion_blocks``: after the block's strided conv (``before_residual``) or after
    its convs (``after_residual``) the BEV map is lifted into the radar points' voxels at the BEV map's
    x/y resolution (``BEV(x, y) + HeightEmb(z)``), fused with the image (SFF / MSDFF) and summed back
    per ``(x, y)``; BEV cells without voxels keep their features and cells with voxels get the sum of
    their fused voxels.

    Args:
        in_channels: point-feature channels.
        grid: pillar grid (one z cell).
        lift_z_size: z size (metres) of the lift voxels.
        pfn_channels: PFN output channels (64).
        layer_nums, layer_strides, num_filters: the 2D blocks (OpenPCDet: 3/5/5, 2/2/2, 64/128/256).
        upsample_strides, num_upsample_filters: the deblocks (1/2/4, 128/128/128).
        num_fusion_blocks, fusion, fusion_position, image_channels, msdff_heads, msdff_points,
        msdff_value_projection, seg_hidden, msdff_value_dim:
            as :class:`SparseFusionBackbone` (at most 3 fusion blocks).
    """

    def __init__(
        self,
        in_channels: int,
        grid: VoxelGrid,
        lift_z_size: float = 0.125,
        pfn_channels: int = 64,
        layer_nums: Sequence[int] = (3, 5, 5),
        layer_strides: Sequence[int] = (2, 2, 2),
        num_filters: Sequence[int] = (64, 128, 256),
        upsample_strides: Sequence[int] = (1, 2, 4),
        num_upsample_filters: Sequence[int] = (128, 128, 128),
        num_fusion_blocks: int = 0,
        fusion: str = "msdff",
        fusion_position: str = "before_residual",
        image_channels: Optional[Sequence[int]] = None,
        msdff_heads: int = 8,
        msdff_points: int = 4,
        msdff_value_projection: str = "after_sampling",
        seg_hidden: Optional[Sequence[int]] = (256, 256),
        msdff_value_dim: Union[int, str, None] = None,
    ) -> None:
        super().__init__()
        _check_fusion_args(num_fusion_blocks, len(layer_nums), fusion, fusion_position)
        if num_fusion_blocks and not image_channels:
            raise MSSFError("image_channels: required (one entry per image level) when num_fusion_blocks > 0")
        if grid.grid_size[2] != 1:
            raise MSSFError(f"grid: expected a pillar grid (one z cell), got grid_size {grid.grid_size}")
        self.grid = grid
        self.num_fusion_blocks, self.fusion_type, self.fusion_position = num_fusion_blocks, fusion, fusion_position
        pcr = grid.point_cloud_range
        self.lift_grid = VoxelGrid(voxel_size=(grid.voxel_size[0], grid.voxel_size[1], float(lift_z_size)), point_cloud_range=pcr)
        self.pfn = PillarFeatureNet(in_channels, pfn_channels, pcr, grid.voxel_size[:2])
        self.down = nn.ModuleList()
        self.convs = nn.ModuleList()
        self.deblocks = nn.ModuleList()
        self.lifts = nn.ModuleList()
        self.fusions = nn.ModuleList()
        self.strides: List[int] = []
        cin, stride = pfn_channels, 1
        _, h, w = grid.spatial_shape
        for i, (n, s, c) in enumerate(zip(layer_nums, layer_strides, num_filters)):
            self.down.append(nn.Sequential(nn.ZeroPad2d(1), nn.Conv2d(cin, c, 3, stride=s, bias=False),
                                           nn.BatchNorm2d(c, eps=1e-3, momentum=0.01), nn.ReLU()))
            self.convs.append(nn.Sequential(*[m for _ in range(n) for m in (
                nn.Conv2d(c, c, 3, padding=1, bias=False), nn.BatchNorm2d(c, eps=1e-3, momentum=0.01), nn.ReLU())]))
            stride *= s
            self.strides.append(stride)
            u = upsample_strides[i]
            self.deblocks.append(nn.Sequential(nn.ConvTranspose2d(c, num_upsample_filters[i], u, stride=u, bias=False),
                                               nn.BatchNorm2d(num_upsample_filters[i], eps=1e-3, momentum=0.01), nn.ReLU()))
            if i < num_fusion_blocks:
                from mssf_blocks.blocks import FusionBlock
                from mssf_blocks.samplers import QueryInit
                from mssf_blocks.lift import PillarLift

                # the lift voxels are already at the BEV map's x/y resolution (see _coarsen), hence stride 1
                self.lifts.append(PillarLift(c, self.lift_grid.spatial_shape[0], stride=1))
                query_init = None
                if fusion == "msdff" and i == 0:
                    query_init = QueryInit(c, image_channels[0], c, pcr)
                self.fusions.append(FusionBlock(_make_fusion(fusion, c, image_channels, msdff_heads, msdff_points,
                                                             msdff_value_projection, msdff_value_dim),
                                                query_init=query_init, position="before_residual"))
            cin = c
        self.bev_channels = sum(num_upsample_filters)
        self.bev_shape = (-(-h // self.strides[0]) * upsample_strides[0], -(-w // self.strides[0]) * upsample_strides[0])
        self.seg_head = None
        if num_fusion_blocks and seg_hidden is not None:
            from mssf_blocks.heads import SemanticGuidedHead

            self.seg_head = SemanticGuidedHead(num_filters[num_fusion_blocks - 1], hidden=tuple(seg_hidden))

    def _fuse(self, i: int, bev: Tensor, lift_voxels: SparseVoxels, fusion_inputs, out: BackboneOutput) -> Tensor:
        v = self.lifts[i](bev, lift_voxels)
        v = self.fusions[i](v, fusion_inputs)
        if i == self.num_fusion_blocks - 1 and self.seg_head is not None:
            out.seg_voxels = v
            v, _, out.seg_logits = self.seg_head(v, return_logits=True)
        out.stages.append(v)
        return replace_occupied_pillars(bev, v, self.lifts[i].stride)

    def voxelize(self, points: Tensor, points_batch: Tensor, batch_size: int):
        """The data-dependent part of :meth:`forward`: ``(pillars, lift voxels of every fusion block)``.

        The pillars are a :class:`~mssf_examples.models.voxelize.Voxelization` of the pillar grid, the lift voxels
        one :class:`SparseVoxels` per fusion block (at its BEV stride). Everything after this has static
        shapes under graph capture: ``mssf_examples.models.export`` runs this eagerly and exports the rest.
        """
        pillars = dynamic_voxelize(points, points_batch, batch_size, self.pfn.grid)
        lifts = []
        if self.num_fusion_blocks:
            vox = dynamic_voxelize(points, points_batch, batch_size, self.lift_grid)
            lift_voxels = SparseVoxels(vox.features[:, :1], vox.coords, batch_size=batch_size, grid=self.lift_grid)
            lifts = [self._coarsen(lift_voxels, self.strides[i]) for i in range(self.num_fusion_blocks)]
        return pillars, lifts

    def forward(self, points: Tensor, points_batch: Tensor, batch_size: int, fusion_inputs=None,
                voxelization=None) -> BackboneOutput:
        """``points (P, C)``, ``points_batch (P,)`` -> :class:`BackboneOutput` with ``bev (B, C, H', W')``.

        ``voxelization``: the output of :meth:`voxelize` when computed already (``None``: computed here).
        """
        if self.num_fusion_blocks and fusion_inputs is None:
            raise MSSFError("fusion_inputs: required when num_fusion_blocks > 0, got None")
        from ..voxelize import pillars_to_bev

        pillars, lifts = self.voxelize(points, points_batch, batch_size) if voxelization is None else voxelization
        x = pillars_to_bev(self.pfn(points, points_batch, batch_size, voxelization=pillars))
        out = BackboneOutput(stages=[])
        ups = []
        for i in range(len(self.down)):
            x = self.down[i](x)
            if i < self.num_fusion_blocks and self.fusion_position == "before_residual":
                x = self._fuse(i, x, lifts[i], fusion_inputs, out)
            x = self.convs[i](x)
            if i < self.num_fusion_blocks and self.fusion_position == "after_residual":
                x = self._fuse(i, x, lifts[i], fusion_inputs, out)
            ups.append(self.deblocks[i](x))
        size = ups[0].shape[-2:]
        ups = [u[..., : size[0], : size[1]] for u in ups]
        out.bev = torch.cat(ups, 1)
        return out

    @staticmethod
    def _coarsen(v: SparseVoxels, s: int) -> SparseVoxels:
        """The lift voxels at the BEV map's x/y resolution (stride ``(1, s, s)``)."""
        c = v.coords.long()
        d, h, w = v.spatial_shape
        hs, ws = -(-h // s), -(-w // s)
        # One int64 key per voxel, monotone in (batch, z, y, x): the same sorted rows as
        # torch.unique(dim=0), several times faster (a 1-d sort instead of a lexicographic one).
        key = ((c[:, 0] * d + c[:, 1]) * hs + torch.div(c[:, 2], s, rounding_mode="floor")) * ws + torch.div(
            c[:, 3], s, rounding_mode="floor")
        key = torch.unique(key)
        c = torch.stack([key // (d * hs * ws), key // (hs * ws) % d, key // ws % hs, key % ws], 1).to(v.coords.dtype)
        return SparseVoxels(
            features=v.features.new_zeros(c.shape[0], 1), coords=c, spatial_shape=(d, -(-h // s), -(-w // s)),
            batch_size=v.batch_size, voxel_size=v.voxel_size, point_range_min=v.point_range_min, stride=(1, s, s),
        )
