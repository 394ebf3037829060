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
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Union

import torch
from torch import Tensor, nn

import spconv.pytorch as spconv

from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse import SparseVoxels

from .spconv_compat import dense, enable_cpu_backward, quiet
from .voxelize import PillarFeatureNet, VoxelGrid, dynamic_voxelize

# spconv's CPU backward needs this on CPU-only torch builds (see spconv_compat).
enable_cpu_backward()

__all__ = [
    "BackboneOutput",
    "SparseBasicBlock",
    "SparseFusionBackbone",
    "SECONDBackbone",
    "CenterPointBackbone",
    "VoxelNeXtBackbone",
    "PointPillarsBackbone",
    "merge_sparse_bev",
    "merge_sparse_bev_dense_reference",
    "FUSION_TYPES",
    "FUSION_POSITIONS",
]

FUSION_TYPES = ("msdff", "sff")


FUSION_POSITIONS = ("before_residual", "after_residual")


def _bn1d(c: int) -> nn.Module:
    # OpenPCDet's sparse-backbone BN settings.
    return nn.BatchNorm1d(c, eps=1e-3, momentum=0.01)


def _subm(cin: int, cout: int, key: str) -> spconv.SparseSequential:
    return spconv.SparseSequential(spconv.SubMConv3d(cin, cout, 3, padding=1, bias=False, indice_key=key), _bn1d(cout), nn.ReLU())


def _down(cin: int, cout: int, key: str, stride=2, padding=1, kernel=3) -> spconv.SparseSequential:
    return spconv.SparseSequential(
        spconv.SparseConv3d(cin, cout, kernel, stride=stride, padding=padding, bias=False, indice_key=key),
        _bn1d(cout),
        nn.ReLU(),
    )


class SparseBasicBlock(spconv.SparseModule):
    """Residual block of two submanifold 3x3x3 convs (identity shortcut)."""

    def __init__(self, channels: int, indice_key: str) -> None:
        super().__init__()
        self.conv1 = spconv.SubMConv3d(channels, channels, 3, padding=1, bias=False, indice_key=indice_key)
        self.bn1 = _bn1d(channels)
        self.conv2 = spconv.SubMConv3d(channels, channels, 3, padding=1, bias=False, indice_key=indice_key)
        self.bn2 = _bn1d(channels)

    def forward(self, x):
        identity = x.features
        out = self.conv1(x)
        out = out.replace_feature(torch.relu(self.bn1(out.features)))
        out = self.conv2(out)
        return out.replace_feature(torch.relu(self.bn2(out.features) + identity))


def _triple(v) -> Tuple[int, int, int]:
    return (v, v, v) if isinstance(v, int) else tuple(v)


def _conv_out_size(size: Tuple[int, int, int], kernel, stride, padding) -> Tuple[int, int, int]:
    k, s, p = _triple(kernel), _triple(stride), _triple(padding)
    return tuple((size[i] + 2 * p[i] - k[i]) // s[i] + 1 for i in range(3))


@dataclass
class _StageSpec:
    channels: int
    downsample: Optional[dict]  # kwargs of _down (stride, padding, kernel) or None
    num_blocks: int
    residual: bool


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
                 value_projection: str = "after_sampling", value_dim: Union[int, str, None] = None):
    from mssf_blocks.fusion import MSDFF, SFF

    if kind == "sff":
        return SFF(list(image_channels), channels)
    if value_dim == "voxel_channels":  # the narrow layout: the image projected to the voxel width first
        value_dim = channels
    elif value_dim is not None and (isinstance(value_dim, bool) or not isinstance(value_dim, int)):
        raise MSSFError(f"msdff_value_dim: expected None, an int or 'voxel_channels', got {value_dim!r}")
    return MSDFF(channels, list(image_channels), value_dim, num_heads=msdff_heads, num_levels=len(image_channels),
                 num_points=msdff_points, value_projection=value_projection)


class SparseFusionBackbone(nn.Module):
    """Sparse 3D backbone: ``conv_input`` then stages; the first ``num_fusion_blocks`` stages fuse images.

    Subclasses fix the stage layout; see :class:`SECONDBackbone`, :class:`CenterPointBackbone`,
    :class:`VoxelNeXtBackbone`.

    Args:
        in_channels: voxel feature channels (the point features).
        grid: the base voxel grid.
        stem_channels: channels of ``conv_input``.
        stages: per-stage layout.
        num_fusion_blocks: ``n``, the number of leading stages that are fusion blocks.
        fusion: ``"msdff"`` or ``"sff"``.
        fusion_position: ``"before_residual"`` (between the downsampling conv and the residual blocks,
            the paper's default) or ``"after_residual"``.
        image_channels: ``C_l`` of every image level (needed when ``num_fusion_blocks > 0``).
        msdff_heads, msdff_points: MSDFF heads and sampling points per level.
        msdff_value_projection: MSDFF's ``value_projection`` (``"after_sampling"`` or
            ``"before_sampling"``; equal results, different cost, see :class:`mssf_blocks.fusion.MSDFF`).
        msdff_value_dim: MSDFF's ``value_dim``: ``None`` (default) the image channels (the paper's and
            the authors' width), ``"voxel_channels"`` each block's voxel channels (the narrow layout),
            or an int.
        seg_hidden: hidden widths of the semantic-guided head (``None`` disables the head).
        z_pad: extra empty z layers on top of the grid (OpenPCDet's ``+1`` so ``41`` z cells downsample
            ``41 -> 21 -> 11 -> 5 -> 2``).
    """

    def __init__(
        self,
        in_channels: int,
        grid: VoxelGrid,
        stem_channels: int,
        stages: Sequence[_StageSpec],
        num_fusion_blocks: int = 0,
        fusion: str = "msdff",
        fusion_position: str = "before_residual",
        image_channels: Optional[Sequence[int]] = None,
        msdff_heads: int = 8,
        msdff_points: int = 4,
        msdff_value_projection: str = "after_sampling",
        seg_hidden: Optional[Sequence[int]] = (256, 256),
        z_pad: int = 0,
        msdff_value_dim: Union[int, str, None] = None,
    ) -> None:
        super().__init__()
        _check_fusion_args(num_fusion_blocks, min(4, len(stages)), fusion, fusion_position)
        if num_fusion_blocks and not image_channels:
            raise MSSFError("image_channels: required (one entry per image level) when num_fusion_blocks > 0")
        self.grid = grid
        self.num_fusion_blocks = num_fusion_blocks
        self.fusion_type, self.fusion_position = fusion, fusion_position
        d, h, w = grid.spatial_shape
        self.input_shape = (d + z_pad, h, w)
        self.conv_input = _subm(in_channels, stem_channels, "subm1")
        self.stages = nn.ModuleList()
        self.strides: List[Tuple[int, int, int]] = []
        self.shapes: List[Tuple[int, int, int]] = []
        self.channels: List[int] = []
        stride, shape, cin = (1, 1, 1), self.input_shape, stem_channels
        for i, spec in enumerate(stages):
            key = f"subm{i + 1}"
            down = None
            if spec.downsample is not None:
                down = _down(cin, spec.channels, f"spconv{i + 1}", **spec.downsample)
                s = _triple(spec.downsample.get("stride", 2))
                shape = _conv_out_size(shape, spec.downsample.get("kernel", 3), s, spec.downsample.get("padding", 1))
                stride = tuple(a * b for a, b in zip(stride, s))
            elif spec.channels != cin:
                raise MSSFError(f"stages[{i}]: a stage without downsampling keeps the channels ({cin}), got {spec.channels}")
            if spec.residual:
                blocks = spconv.SparseSequential(*[SparseBasicBlock(spec.channels, key) for _ in range(spec.num_blocks)])
            else:
                blocks = spconv.SparseSequential(*[_subm(spec.channels, spec.channels, key) for _ in range(spec.num_blocks)])
            if i < num_fusion_blocks:
                from mssf_blocks.blocks import FusionBlock
                from mssf_blocks.fusion import QueryInit

                query_init = None
                if fusion == "msdff" and i == 0:
                    query_init = QueryInit(spec.channels, image_channels[0], spec.channels, grid.point_cloud_range)
                stage = FusionBlock(
                    _make_fusion(fusion, spec.channels, image_channels, msdff_heads, msdff_points,
                                 msdff_value_projection, msdff_value_dim),
                    downsample=down,
                    blocks=blocks,
                    position=fusion_position,
                    query_init=query_init,
                    downsample_stride=(_triple(spec.downsample.get("stride", 2)) if down is not None else None),
                )
            else:
                stage = _OrdinaryStage(down, blocks)
            self.stages.append(stage)
            self.strides.append(stride)
            self.shapes.append(shape)
            self.channels.append(spec.channels)
            cin = spec.channels
        self.seg_head = None
        if num_fusion_blocks and seg_hidden is not None:
            from mssf_blocks.heads import SemanticGuidedHead

            self.seg_head = SemanticGuidedHead(self.channels[num_fusion_blocks - 1], hidden=tuple(seg_hidden))

    def _wrap(self, t, stride) -> SparseVoxels:
        return SparseVoxels.from_spconv(t, self.grid.voxel_size, self.grid.point_range_min, stride)

    def forward_stages(self, voxels: SparseVoxels, fusion_inputs=None) -> BackboneOutput:
        """Run ``conv_input`` and every stage.

        Args:
            voxels: input voxels on :attr:`grid` (``(N, in_channels)`` features).
            fusion_inputs: :class:`mssf_blocks.fusion.FusionInputs` (required when fusing).
        """
        if self.num_fusion_blocks and fusion_inputs is None:
            raise MSSFError("fusion_inputs: required when num_fusion_blocks > 0, got None")
        with quiet():  # spconv's own torch.fx / indexing messages (see mssf_blocks.compat.spconv)
            return self._forward_stages(voxels, fusion_inputs)

    def _forward_stages(self, voxels: SparseVoxels, fusion_inputs) -> BackboneOutput:
        x = spconv.SparseConvTensor(voxels.features, voxels.coords, list(self.input_shape), voxels.batch_size)
        x = self.conv_input(x)
        outs: List[SparseVoxels] = []
        seg_logits = seg_voxels = None
        for i, stage in enumerate(self.stages):
            if i < self.num_fusion_blocks:
                prev = self.strides[i - 1] if i else (1, 1, 1)
                v = stage(self._wrap(x, prev), fusion_inputs)
                if i == self.num_fusion_blocks - 1 and self.seg_head is not None:
                    seg_voxels = v
                    v, _, seg_logits = self.seg_head(v, return_logits=True)
                x = v.to_spconv()
            else:
                x = stage(x)
            outs.append(self._wrap(x, self.strides[i]))
        return BackboneOutput(stages=outs, seg_logits=seg_logits, seg_voxels=seg_voxels)


class _OrdinaryStage(nn.Module):
    """An ordinary block: optional downsampling sparse conv, then submanifold / residual blocks."""

    def __init__(self, downsample, blocks) -> None:
        super().__init__()
        self.downsample = downsample
        self.blocks = blocks

    def forward(self, x):
        if self.downsample is not None:
            x = self.downsample(x)
        return self.blocks(x)


def _second_stages(channels: Sequence[int], residual: bool) -> List[_StageSpec]:
    c1, c2, c3, c4 = channels
    return [
        # VoxelBackBone8x: one SubM in conv1; VoxelResBackBone8x: two residual blocks
        _StageSpec(c1, None, 2 if residual else 1, residual),
        _StageSpec(c2, dict(stride=2, padding=1), 2, residual),
        _StageSpec(c3, dict(stride=2, padding=1), 2, residual),
        # no z padding here: with 41 z cells 11 -> 5 (OpenPCDet's layout)
        _StageSpec(c4, dict(stride=2, padding=(0, 1, 1)), 2, residual),
    ]


class _DenseBEVBackbone(SparseFusionBackbone):
    """SECOND/CenterPoint layout: stages, then ``conv_out`` (z-stride 2) and a dense BEV map."""

    def __init__(self, in_channels, grid, channels, out_channels, residual, **kwargs) -> None:
        if len(channels) != 5:
            raise MSSFError(f"channels: expected 5 values (stem, stage1..4), got {channels!r}")
        super().__init__(in_channels, grid, channels[0], _second_stages(channels[1:], residual), z_pad=1, **kwargs)
        self.conv_out = _down(channels[4], out_channels, "spconv_down2", stride=(2, 1, 1), padding=0, kernel=(3, 1, 1))
        d_out = _conv_out_size(self.shapes[-1], (3, 1, 1), (2, 1, 1), 0)
        if min(d_out) < 1:
            raise MSSFError(
                f"grid: the z extent ({grid.spatial_shape[0]} cells) is too small for the SECOND layout "
                f"(4 z-downsamplings); use at least 24 z cells"
            )
        self.bev_channels = out_channels * d_out[0]
        self.bev_shape = d_out[1:]

    def forward(self, voxels: SparseVoxels, fusion_inputs=None) -> BackboneOutput:
        out = self.forward_stages(voxels, fusion_inputs)
        with quiet():
            x = self.conv_out(out.stages[-1].to_spconv())
        out.bev = dense(x).flatten(1, 2)  # (B, C, D, H, W) -> (B, C * D, H, W)
        return out


class SECONDBackbone(_DenseBEVBackbone):
    """SECOND's ``VoxelBackBone8x``: stem 16, stages 16/32/64/64 (submanifold convs), ``conv_out`` 128.

    Args:
        in_channels: point-feature channels.
        grid: base voxel grid.
        channels: ``(stem, stage1, stage2, stage3, stage4)``; default ``(16, 16, 32, 64, 64)``.
        out_channels: ``conv_out`` channels (BEV channels = ``out_channels * D_out``).
        **kwargs: fusion settings of :class:`SparseFusionBackbone`.
    """

    def __init__(self, in_channels: int, grid: VoxelGrid, channels=(16, 16, 32, 64, 64), out_channels: int = 128, **kwargs):
        super().__init__(in_channels, grid, tuple(channels), out_channels, residual=False, **kwargs)


class CenterPointBackbone(_DenseBEVBackbone):
    """CenterPoint's ``VoxelResBackBone8x``: stem 16, residual stages 16/32/64/128, ``conv_out`` 128."""

    def __init__(self, in_channels: int, grid: VoxelGrid, channels=(16, 16, 32, 64, 128), out_channels: int = 128, **kwargs):
        super().__init__(in_channels, grid, tuple(channels), out_channels, residual=True, **kwargs)


def merge_sparse_bev(
    tensors: Sequence[Tuple[Tensor, Tensor]], factors: Sequence[int], batch_size: int, bev_shape: Tuple[int, int]
) -> Tuple[Tensor, Tensor]:
    """VoxelNeXt's sparse height compression: align strides, sum features with equal ``(b, y, x)``.

    Args:
        tensors: per stage ``(features (N_i, C), coords (N_i, 4) (b, z, y, x))``.
        factors: per stage, its stride relative to the first (coords ``y, x`` are multiplied by it).
        batch_size: ``B``.
        bev_shape: ``(H, W)`` of the first stage.

    Returns:
        ``features (M, C)`` and ``coords (M, 3)`` int32 ``(b, y, x)``, sorted by ``(b, y, x)``.
    """
    h, w = bev_shape
    feats, keys = [], []
    for (f, c), k in zip(tensors, factors):
        c = c.long()
        y, x = c[:, 2] * k, c[:, 3] * k
        if c.numel() and (int(y.max()) >= h or int(x.max()) >= w):
            raise MSSFError(f"tensors: scaled coords exceed the BEV shape {bev_shape} (factor {k})")
        feats.append(f)
        keys.append((c[:, 0] * h + y) * w + x)
    f = torch.cat(feats)
    key = torch.cat(keys)
    uniq, inv = torch.unique(key, sorted=True, return_inverse=True)
    out = f.new_zeros(uniq.numel(), f.shape[1]).index_add_(0, inv, f)
    coords = torch.stack([uniq // (h * w), (uniq // w) % h, uniq % w], 1).int()
    return out, coords


def merge_sparse_bev_dense_reference(
    tensors: Sequence[Tuple[Tensor, Tensor]], factors: Sequence[int], batch_size: int, bev_shape: Tuple[int, int]
) -> Tensor:
    """Dense reference of :func:`merge_sparse_bev`: scatter-add every voxel into ``(B, C, H, W)``."""
    h, w = bev_shape
    c = tensors[0][0].shape[1]
    bev = tensors[0][0].new_zeros(batch_size, c, h, w)
    for (f, co), k in zip(tensors, factors):
        for row in range(co.shape[0]):
            b, _, y, x = (int(v) for v in co[row])
            bev[b, :, y * k, x * k] += f[row]
    return bev


class VoxelNeXtBackbone(SparseFusionBackbone):
    """VoxelNeXt: six residual stages (the paper doubles VoxelNeXt's 16/32/64/128/128/128 channels).

    Stages 4-6 (strides 8, 16, 32) are merged into a sparse BEV at stride 8 (:func:`merge_sparse_bev`),
    followed by a 3x3 submanifold 2D conv (``conv_out``).

    Args:
        in_channels: point-feature channels.
        grid: base voxel grid.
        channels: ``(stem, stage1, ..., stage6)``; default the paper's doubled ``(32, 32, 64, 128, 256, 256, 256)``.
        out_channels: sparse BEV channels after ``conv_out``.
        **kwargs: fusion settings of :class:`SparseFusionBackbone`.
    """

    def __init__(self, in_channels: int, grid: VoxelGrid, channels=(32, 32, 64, 128, 256, 256, 256), out_channels: int = 256, **kwargs):
        channels = tuple(channels)
        if len(channels) != 7 or channels[4] != channels[5] or channels[5] != channels[6]:
            raise MSSFError(f"channels: expected 7 values (stem, stage1..6) with stages 4-6 equal, got {channels!r}")
        stages = [_StageSpec(channels[1], None, 2, True)] + [
            _StageSpec(channels[i], dict(stride=2, padding=1), 2, True) for i in range(2, 7)
        ]
        super().__init__(in_channels, grid, channels[0], stages, **kwargs)
        self.bev_shape = self.shapes[3][1:]
        self.conv_out = spconv.SparseSequential(
            spconv.SubMConv2d(channels[4], out_channels, 3, padding=1, bias=False, indice_key="subm_bev"),
            _bn1d(out_channels),
            nn.ReLU(),
        )
        self.bev_channels = out_channels

    def forward(self, voxels: SparseVoxels, fusion_inputs=None) -> BackboneOutput:
        out = self.forward_stages(voxels, fusion_inputs)
        s4, s5, s6 = out.stages[3:6]
        feats, coords = merge_sparse_bev(
            [(s4.features, s4.coords), (s5.features, s5.coords), (s6.features, s6.coords)],
            [1, 2, 4], voxels.batch_size, self.bev_shape,
        )
        with quiet():
            t = self.conv_out(spconv.SparseConvTensor(feats, coords, list(self.bev_shape), voxels.batch_size))
        out.sparse_bev = (t.features, t.indices)
        return out


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
        self.lift_grid = VoxelGrid(pcr, (grid.voxel_size[0], grid.voxel_size[1], float(lift_z_size)))
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
                from mssf_blocks.fusion import QueryInit
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
        summed = self.lifts[i].to_bev(v)
        occupied = self.lifts[i].to_bev(v.replace(features=v.features.new_ones(v.num_voxels, 1))) > 0
        return torch.where(occupied, summed, bev)

    def voxelize(self, points: Tensor, points_batch: Tensor, batch_size: int):
        """The data-dependent part of :meth:`forward`: ``(pillars, lift voxels of every fusion block)``.

        The pillars are a :class:`~mssf_examples.voxelize.Voxelization` of the pillar grid, the lift voxels
        one :class:`SparseVoxels` per fusion block (at its BEV stride). Everything after this has static
        shapes under graph capture: ``mssf_examples.export`` runs this eagerly and exports the rest.
        """
        pillars = dynamic_voxelize(points, points_batch, batch_size, self.pfn.grid)
        lifts = []
        if self.num_fusion_blocks:
            vox = dynamic_voxelize(points, points_batch, batch_size, self.lift_grid)
            lift_voxels = self.lift_grid.sparse_voxels(vox.features[:, :1], vox.coords, batch_size)
            lifts = [self._coarsen(lift_voxels, self.strides[i]) for i in range(self.num_fusion_blocks)]
        return pillars, lifts

    def forward(self, points: Tensor, points_batch: Tensor, batch_size: int, fusion_inputs=None,
                voxelization=None) -> BackboneOutput:
        """``points (P, C)``, ``points_batch (P,)`` -> :class:`BackboneOutput` with ``bev (B, C, H', W')``.

        ``voxelization``: the output of :meth:`voxelize` when computed already (``None``: computed here).
        """
        if self.num_fusion_blocks and fusion_inputs is None:
            raise MSSFError("fusion_inputs: required when num_fusion_blocks > 0, got None")
        from .voxelize import pillars_to_bev

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
