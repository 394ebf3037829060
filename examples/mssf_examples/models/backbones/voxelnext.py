"""VoxelNeXt (Chen et al. 2023) with MSSF fusion blocks, and its sparse BEV merge (spconv).

Import these names from :mod:`mssf_examples.models.backbones`.
"""

from __future__ import annotations

from typing import Sequence, Tuple

import torch
from torch import Tensor, nn

import spconv.pytorch as spconv

from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse_voxels import SparseVoxels

from ..spconv_helpers import quiet
from ..voxelize import VoxelGrid
from .fusion_stage import BackboneOutput
from .voxel import SparseFusionBackbone, _bn1d, _StageSpec

__all__ = ["VoxelNeXtBackbone", "merge_sparse_bev", "merge_sparse_bev_dense_reference"]


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


class _SubMConv2dBias(spconv.SubMConv2d):
    """``SubMConv2d`` with a bias that also runs in eval mode on the CPU: spconv 2.3 adds the bias
    inside its inference kernel, which asserts on CPU tensors ("cpu don't support act and bias"); here
    the convolution runs without it and the bias is added after (the same sum)."""

    def forward(self, input, add_input=None):
        if self.bias is None or input.features.is_cuda:
            return super().forward(input, add_input)
        out = self._conv_forward(self.training, input, self.weight, None, add_input, name=self.name,
                                 sparse_unique_name=self._sparse_unique_name, act_type=self.act_type,
                                 act_alpha=self.act_alpha, act_beta=self.act_beta)
        return out.replace_feature(out.features + self.bias)


class VoxelNeXtBackbone(SparseFusionBackbone):
    """VoxelNeXt: six residual stages (the paper doubles VoxelNeXt's 16/32/64/128/128/128 channels).

    Stages 4-6 (strides 8, 16, 32) are merged into a sparse BEV at stride 8 (:func:`merge_sparse_bev`),
    followed by a 3x3 submanifold 2D conv (``conv_out``).

    Args:
        in_channels: point-feature channels.
        grid: base voxel grid.
        channels: ``(stem, stage1, ..., stage6)``; default the paper's doubled ``(32, 32, 64, 128, 256, 256, 256)``.
        out_channels: sparse BEV channels after ``conv_out``.
        authors_layout: the authors' ``SparseEncoderVoxelNeXtFuse``: ``conv_out`` a regular (not
            submanifold) ``SparseConv2d``, then ``shared_conv`` (``SubMConv2d`` with bias, ``BN(eps=1e-5)``,
            ReLU), z padded by one cell (their ``sparse_shape`` 41), and the fusion modules with their
            forward (``authors_switches``); their checkpoints load through ``mssf_examples.models.authors_checkpoint``.
        **kwargs: fusion settings of :class:`SparseFusionBackbone`.
    """

    def __init__(self, in_channels: int, grid: VoxelGrid, channels=(32, 32, 64, 128, 256, 256, 256), out_channels: int = 256,
                 authors_layout: bool = False, **kwargs):
        channels = tuple(channels)
        if len(channels) != 7 or channels[4] != channels[5] or channels[5] != channels[6]:
            raise MSSFError(f"channels: expected 7 values (stem, stage1..6) with stages 4-6 equal, got {channels!r}")
        stages = [_StageSpec(channels[1], None, 2, True)] + [
            _StageSpec(channels[i], dict(stride=2, padding=1), 2, True) for i in range(2, 7)
        ]
        if authors_layout:
            kwargs = dict(kwargs, authors_switches=True, z_pad=1)
        super().__init__(in_channels, grid, channels[0], stages, **kwargs)
        self.authors_layout = bool(authors_layout)
        self.bev_shape = self.shapes[3][1:]
        conv = spconv.SparseConv2d if authors_layout else spconv.SubMConv2d
        self.conv_out = spconv.SparseSequential(
            conv(channels[4], out_channels, 3, padding=1, bias=False, indice_key="subm_bev"),
            _bn1d(out_channels),
            nn.ReLU(),
        )
        self.shared_conv = None
        if authors_layout:
            self.shared_conv = spconv.SparseSequential(
                _SubMConv2dBias(out_channels, out_channels, 3, padding=1, bias=True, indice_key="subm_shared"),
                nn.BatchNorm1d(out_channels, eps=1e-5, momentum=0.1),
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
            if self.shared_conv is not None:
                t = self.shared_conv(t)
        out.sparse_bev = (t.features, t.indices)
        return out
