"""MSSF-PP in the authors' layout (``EricLiuhhh/MSSF``: ``PointPillarsScatterFuse`` + ``SECONDFuse`` +
``SECONDFPN``, config ``pointpillars_hv_secfpn_8xb6-160e_vod-3d-3class_mm_bb_bevfeat_lr0001``).

Two :class:`mssf_blocks.blocks.pillar_fusion_stage.PillarFusionStage` s with the ``OFFICIAL_SWITCHES`` of
``mssf_blocks.weights.authors_checkpoint`` (``docs/differences.md`` rows 15-18):

* ``scatter_stage``, before any BEV block: the radar points voxelised on the pillar x/y cells and
  ``lift_z_size`` in z, ``conv_input`` of their mean features only (no BEV term), fused, and the summed
  voxels concatenated after the PFN's scattered map (``C_pfn + C_0`` channels);
* ``backbone_stage``, after the whole first block: voxels on twice the pillar x/y cells,
  ``conv_input + BEV + HeightEmb``, ``BEV`` added to the query, concatenated after the block's output.

Then the remaining blocks and the ``SECONDFPN`` deblocks. Module names follow theirs (``blocks.<i>.<j>``
as their ``SECONDFuse.blocks``, ``deblocks.<i>`` as ``SECONDFPN.deblocks``) so a checkpoint maps by
prefix (:mod:`mssf_examples.models.authors_checkpoint`). Their voxelisation caps a voxel at 32 points
(``max_num_points``) before averaging; ours averages all (radar voxels rarely hold more).
"""

from __future__ import annotations

import functools

from typing import List, Sequence

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse_voxels import SparseVoxels

from ..voxelize import PillarFeatureNet, VoxelGrid, dynamic_voxelize, pillars_to_bev
from .fusion_stage import BackboneOutput

__all__ = ["AuthorsPointPillarsBackbone"]


def _bn2d(c: int) -> nn.Module:
    return nn.BatchNorm2d(c, eps=1e-3, momentum=0.01)


class AuthorsPointPillarsBackbone(nn.Module):
    """The authors' MSSF-PP backbone: PFN, two concatenating pillar fusion stages, three blocks, deblocks.

    Args:
        in_channels: point-feature channels (VoD: 7).
        grid: the pillar grid (one z cell; VoD 0.16 x 0.16 m).
        image_channels: ``C`` of every image level (theirs: five FPN levels of 256).
        lift_z_size: z size of the lift voxels (0.125 m).
        z_pad: extra z cells of their sparse shape (``41`` for 40 cells: the height embedding's rows).
        pfn_channels, stage_channels: 64 and 64 (their ``base_channels``).
        layer_nums, layer_strides, out_channels: their ``SECONDFuse`` blocks (3/5/5, 2/2/2, 64/128/256).
        upsample_strides, upsample_channels: their ``SECONDFPN`` (1/2/4, 128 each).
        msdff_heads, msdff_points: their ``MSDeformableAttention`` (8 heads, 4 points).
        seg_hidden: the semantic heads' hidden widths (their ``ForegroundSegmentationHead``: 256, 256).
        max_points: their ``max_num_points`` (32): the PFN's zero-padded rows (``PillarFeatureNet(max_points=)``).
    """

    def __init__(
        self,
        in_channels: int,
        grid: VoxelGrid,
        image_channels: Sequence[int],
        lift_z_size: float = 0.125,
        z_pad: int = 1,
        pfn_channels: int = 64,
        stage_channels: int = 64,
        layer_nums: Sequence[int] = (3, 5, 5),
        layer_strides: Sequence[int] = (2, 2, 2),
        out_channels: Sequence[int] = (64, 128, 256),
        upsample_strides: Sequence[int] = (1, 2, 4),
        upsample_channels: Sequence[int] = (128, 128, 128),
        msdff_heads: int = 8,
        msdff_points: int = 4,
        seg_hidden: Sequence[int] = (256, 256),
        max_points: int = 32,
    ) -> None:
        super().__init__()
        from mssf_blocks.blocks import FusionBlock
        from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES as SW
        from mssf_blocks.samplers import MSDFF, QueryInit
        from mssf_blocks.geometry import VoxelCentroidProjector
        from mssf_blocks.heads import SemanticGuidedHead
        from mssf_blocks.lift import PillarLift
        from mssf_blocks.blocks.pillar_fusion_stage import PillarFusionStage

        if grid.grid_size[2] != 1:
            raise MSSFError(f"grid: expected a pillar grid (one z cell), got grid_size {grid.grid_size}")
        if not image_channels:
            raise MSSFError("image_channels: expected one entry per image level, got none")
        if out_channels[0] != stage_channels:
            raise MSSFError(f"out_channels: block 0 must give the stage's {stage_channels} channels, got {out_channels}")
        pcr = grid.point_cloud_range
        self.grid, self.z_pad = grid, int(z_pad)
        vx, vy, _ = grid.voxel_size
        self.lift_grids = [VoxelGrid(voxel_size=(vx, vy, float(lift_z_size)), point_cloud_range=pcr), VoxelGrid(voxel_size=(2 * vx, 2 * vy, float(lift_z_size)), point_cloud_range=pcr)]
        num_z = self.lift_grids[0].spatial_shape[0] + self.z_pad
        # mmdet3d's PFN norm: BN1d(eps=1e-3, momentum=0.01)
        self.pfn = PillarFeatureNet(in_channels, pfn_channels, pcr, (vx, vy), max_points=max_points,
                                    norm_layer=functools.partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01))
        c = stage_channels
        levels = list(image_channels)

        def stage(raw_lift_kw, stage_kw):
            block = FusionBlock(
                MSDFF(levels, c, num_heads=msdff_heads, num_levels=len(levels), num_points=msdff_points, **SW["msdff"]),
                query_init=QueryInit(c, levels[0], c, pcr, **SW["query_init"]),
                projector=VoxelCentroidProjector(**SW["projector"]),
                semantic_head=SemanticGuidedHead(c, hidden=tuple(seg_hidden)), **SW["fusion_block"])
            return PillarFusionStage(PillarLift(c, num_z, raw_channels=in_channels, **raw_lift_kw), block, **stage_kw)

        self.scatter_stage = stage(SW["pillar_scatter_lift"], SW["pillar_scatter_stage"])
        self.backbone_stage = stage(SW["pillar_lift"], SW["pillar_stage"])
        ins = [pfn_channels + c, out_channels[0] + c] + list(out_channels[1:-1])
        self.blocks = nn.ModuleList()
        for cin, cout, n, s in zip(ins, out_channels, layer_nums, layer_strides):
            layers: List[nn.Module] = [nn.Conv2d(cin, cout, 3, stride=s, padding=1, bias=False), _bn2d(cout), nn.ReLU()]
            for _ in range(n):
                layers += [nn.Conv2d(cout, cout, 3, padding=1, bias=False), _bn2d(cout), nn.ReLU()]
            self.blocks.append(nn.Sequential(*layers))
        self.deblocks = nn.ModuleList(
            nn.Sequential(nn.ConvTranspose2d(cout, u, k, stride=k, bias=False), _bn2d(u), nn.ReLU())
            for cout, u, k in zip([out_channels[0] + c] + list(out_channels[1:]), upsample_channels, upsample_strides))
        _, h, w = grid.spatial_shape
        self.bev_channels = sum(upsample_channels)
        self.bev_shape = (-(-h // layer_strides[0]) * upsample_strides[0], -(-w // layer_strides[0]) * upsample_strides[0])

    @property
    def seg_head(self):
        """The supervised semantic head (``SECONDFuse``'s; the middle encoder's is not: differences row 23)."""
        return self.backbone_stage.block.semantic_head

    def _lift_voxels(self, points: Tensor, points_batch: Tensor, batch_size: int, k: int) -> SparseVoxels:
        g = self.lift_grids[k]
        vox = dynamic_voxelize(points, points_batch, batch_size, g)
        d, h, w = g.spatial_shape
        return SparseVoxels(vox.features, vox.coords, (d + self.z_pad, h, w), batch_size, voxel_size=g.voxel_size,
                            point_range_min=g.point_range_min)

    def forward(self, points: Tensor, points_batch: Tensor, batch_size: int, fusion_inputs=None,
                voxelization=None) -> BackboneOutput:
        if fusion_inputs is None:
            raise MSSFError("fusion_inputs: the authors' MSSF-PP always fuses; got None")
        x = pillars_to_bev(self.pfn(points, points_batch, batch_size))
        out = BackboneOutput(stages=[])
        x = self.scatter_stage(x, self._lift_voxels(points, points_batch, batch_size, 0), fusion_inputs)
        ups = []
        for i, block in enumerate(self.blocks):
            x = block(x)
            if i == 0:
                v = self._lift_voxels(points, points_batch, batch_size, 1)
                x, out.seg_voxels, out.seg_logits = self.backbone_stage(x, v, fusion_inputs, return_logits=True)
            ups.append(self.deblocks[i](x))
        size = ups[0].shape[-2:]
        out.bev = torch.cat([u[..., : size[0], : size[1]] for u in ups], 1)
        return out

