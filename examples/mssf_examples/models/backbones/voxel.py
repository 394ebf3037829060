"""Sparse 3D voxel backbones with MSSF fusion blocks (spconv), laid out as in OpenPCDet.

The spconv building blocks (submanifold / strided sparse convs, :class:`SparseBasicBlock`), the generic
:class:`SparseFusionBackbone` and the dense-BEV layouts :class:`SECONDBackbone` (``VoxelBackBone8x``)
and :class:`CenterPointBackbone` (``VoxelResBackBone8x``). Import them from :mod:`mssf_examples.models.backbones`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Union

import torch
from torch import nn

import spconv.pytorch as spconv

from mssf_blocks.checks.spconv_inputs import check_spconv_input
from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse_voxels import SparseVoxels

from ..spconv_helpers import dense, enable_cpu_backward, quiet
from ..voxelize import VoxelGrid
from .fusion_stage import BackboneOutput, _check_fusion_args, _make_fusion

# spconv's CPU backward needs this on CPU-only torch builds (see spconv_compat).
enable_cpu_backward()

__all__ = ["SparseBasicBlock", "SparseFusionBackbone", "SECONDBackbone", "CenterPointBackbone"]


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
            ``"before_sampling"``; equal results, different cost, see :class:`mssf_blocks.samplers.MSDFF`).
        msdff_value_dim: MSDFF's ``value_dim``: ``None`` (default) the image channels (the paper's and
            the authors' width), ``"voxel_channels"`` each block's voxel channels (the narrow layout),
            or an int.
        seg_hidden: hidden widths of the semantic-guided head (``None`` disables the head).
        head_position: where the head reads the last fusion block's voxels: ``"after_fusion"`` (the
            fused features before the block's residual blocks: the paper's eq. 12-13 and the authors'
            ``SparseEncoderVoxelNeXtFuse``) or ``"after_residual"`` (the block's output); see
            :class:`mssf_blocks.blocks.FusionBlock`.
        authors_switches: build the fusion modules, query initialiser and projector with
            ``mssf_blocks.weights.authors_checkpoint.OFFICIAL_SWITCHES`` (the authors' forward).
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
        head_position: str = "after_fusion",
        authors_switches: bool = False,
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
                from mssf_blocks.samplers import QueryInit
                from mssf_blocks.heads import SemanticGuidedHead

                head = None
                if i == num_fusion_blocks - 1 and seg_hidden is not None:
                    # the semantic-guided head runs inside the last fusion block (paper Sec. III-D)
                    head = SemanticGuidedHead(spec.channels, hidden=tuple(seg_hidden))
                from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES as SW
                from mssf_blocks.geometry import VoxelCentroidProjector

                query_init = None
                if fusion == "msdff" and i == 0:
                    query_init = QueryInit(spec.channels, image_channels[0], spec.channels, grid.point_cloud_range,
                                           **(SW["query_init"] if authors_switches else {}))
                stage = FusionBlock(
                    _make_fusion(fusion, spec.channels, image_channels, msdff_heads, msdff_points,
                                 msdff_value_projection, msdff_value_dim, authors_switches),
                    projector=VoxelCentroidProjector(**SW["projector"]) if authors_switches else None,
                    downsample=down,
                    blocks=blocks,
                    position=fusion_position,
                    query_init=query_init,
                    downsample_stride=(_triple(spec.downsample.get("stride", 2)) if down is not None else None),
                    semantic_head=head,
                    head_position=head_position,
                )
            else:
                stage = _OrdinaryStage(down, blocks)
            self.stages.append(stage)
            self.strides.append(stride)
            self.shapes.append(shape)
            self.channels.append(spec.channels)
            cin = spec.channels
        self.head_position = head_position

    @property
    def seg_head(self):
        """The semantic-guided head (held by the last fusion block), or ``None``."""
        return self.stages[self.num_fusion_blocks - 1].semantic_head if self.num_fusion_blocks else None

    def _wrap(self, t, stride) -> SparseVoxels:
        return SparseVoxels.from_spconv(t, voxel_size=self.grid.voxel_size, point_range_min=self.grid.point_range_min,
                                        stride=stride)

    def forward_stages(self, voxels: SparseVoxels, fusion_inputs=None) -> BackboneOutput:
        """Run ``conv_input`` and every stage.

        Args:
            voxels: input voxels on :attr:`grid` (``(N, in_channels)`` features).
            fusion_inputs: :class:`mssf_blocks.samplers.FusionInputs` (required when fusing).
        """
        if self.num_fusion_blocks and fusion_inputs is None:
            raise MSSFError("fusion_inputs: required when num_fusion_blocks > 0, got None")
        with quiet():  # spconv's own torch.fx / indexing messages (see mssf_blocks.integrations.spconv)
            return self._forward_stages(voxels, fusion_inputs)

    def _forward_stages(self, voxels: SparseVoxels, fusion_inputs) -> BackboneOutput:
        # our error before spconv's own (float64 features, int64 indices, no voxel, a permuted grid)
        check_spconv_input(voxels.features, voxels.coords, voxels.spatial_shape, voxels.batch_size,
                           expected_shape=self.grid.spatial_shape, module=self.conv_input, module_name="conv_input")
        x = spconv.SparseConvTensor(voxels.features, voxels.coords, list(self.input_shape), voxels.batch_size)
        x = self.conv_input(x)
        outs: List[SparseVoxels] = []
        seg_logits = seg_voxels = None
        for i, stage in enumerate(self.stages):
            if i < self.num_fusion_blocks:
                prev = self.strides[i - 1] if i else (1, 1, 1)
                if stage.semantic_head is not None:
                    v, seg_voxels, seg_logits = stage(self._wrap(x, prev), fusion_inputs, return_logits=True)
                else:
                    v = stage(self._wrap(x, prev), fusion_inputs)
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
