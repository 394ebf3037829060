"""Swap stage ``conv2`` of an OpenPCDet-style ``VoxelResBackBone8x`` for an MSSF fusion block.

The backbone below is written in a few lines with spconv, with the layer layout of OpenPCDet's
``VoxelResBackBone8x`` (``SubMConv3d`` input layer, ``SparseBasicBlock`` residual blocks, stride-2
``SparseConv3d`` "post-act" blocks opening each stage, ``indice_key`` s ``subm1``, ``res1``,
``spconv2``, ``res2``, ...). :func:`swap_conv2_for_fusion` then replaces ``conv2`` by a
:class:`~mssf_blocks.blocks.FusionBlock` that keeps the stage's own downsample block and residual
blocks and inserts MSDFF image fusion between them - the paper's fusion block. The only change to the
backbone's ``forward`` is passing the camera inputs to stages that are fusion blocks.

Runs on CPU in a few seconds with random radar points and random FPN features::

    python examples/swap_openpcdet_stage.py

Notes: spconv 2.3 on CPU supports no bias in sparse convolutions, so this demo builds bias-free
convolutions; it runs forward only (on a CPU-only torch, spconv's backward needs
``mssf_blocks.integrations.spconv.enable_cpu_backward()`` first, as in the README's drop-in snippet).
"""

from __future__ import annotations

import time
from typing import Dict, Optional, Sequence

import torch
from torch import nn

import spconv.pytorch as spconv
from mssf_blocks import VoxelGrid
from mssf_blocks.blocks import FusionBlock
from mssf_blocks.integrations.spconv import quiet
from mssf_blocks.samplers import MSDFF, FusionInputs

POINT_CLOUD_RANGE = (0.0, -25.6, -3.0, 51.2, 25.6, 2.0)  # (x_min, y_min, z_min, x_max, y_max, z_max)
VOXEL_SIZE = (0.4, 0.4, 0.125)  # (x, y, z); the paper uses 0.05 m in x, y - coarser keeps the demo fast
IMAGE_SIZE = (160, 256)  # (H, W)
FPN_STRIDES = (4, 8, 16, 32)
FPN_CHANNELS = 32


# --------------------------------------------------------------------------------------------------
# An OpenPCDet-style VoxelResBackBone8x, in a few lines
# --------------------------------------------------------------------------------------------------
def _bn(c: int) -> nn.BatchNorm1d:
    return nn.BatchNorm1d(c, eps=1e-3, momentum=0.01)


def post_act_block(cin, cout, kernel, stride=1, padding=0, indice_key=None, conv_type="subm"):
    conv = (
        spconv.SubMConv3d(cin, cout, kernel, bias=False, indice_key=indice_key)
        if conv_type == "subm"
        else spconv.SparseConv3d(cin, cout, kernel, stride=stride, padding=padding, bias=False, indice_key=indice_key)
    )
    return spconv.SparseSequential(conv, _bn(cout), nn.ReLU())


class SparseBasicBlock(spconv.SparseModule):
    """Two 3x3x3 submanifold convs with a residual connection (OpenPCDet's ``SparseBasicBlock``)."""

    def __init__(self, channels: int, indice_key: str) -> None:
        super().__init__()
        self.conv1 = spconv.SubMConv3d(channels, channels, 3, padding=1, bias=False, indice_key=indice_key)
        self.bn1 = _bn(channels)
        self.conv2 = spconv.SubMConv3d(channels, channels, 3, padding=1, bias=False, indice_key=indice_key)
        self.bn2 = _bn(channels)
        self.relu = nn.ReLU()

    def forward(self, x):
        identity = x.features
        out = self.conv1(x)
        out = out.replace_feature(self.relu(self.bn1(out.features)))
        out = self.conv2(out)
        return out.replace_feature(self.relu(self.bn2(out.features) + identity))


class VoxelResBackBone8x(nn.Module):
    def __init__(self, input_channels: int, grid_size: Sequence[int]) -> None:
        super().__init__()
        gx, gy, gz = grid_size
        self.sparse_shape = [gz + 1, gy, gx]  # OpenPCDet pads z by one
        self.conv_input = spconv.SparseSequential(
            spconv.SubMConv3d(input_channels, 16, 3, padding=1, bias=False, indice_key="subm1"), _bn(16), nn.ReLU()
        )
        self.conv1 = spconv.SparseSequential(SparseBasicBlock(16, "res1"), SparseBasicBlock(16, "res1"))
        self.conv2 = spconv.SparseSequential(
            post_act_block(16, 32, 3, stride=2, padding=1, indice_key="spconv2", conv_type="spconv"),
            SparseBasicBlock(32, "res2"), SparseBasicBlock(32, "res2"),
        )
        self.conv3 = spconv.SparseSequential(
            post_act_block(32, 64, 3, stride=2, padding=1, indice_key="spconv3", conv_type="spconv"),
            SparseBasicBlock(64, "res3"), SparseBasicBlock(64, "res3"),
        )
        self.conv4 = spconv.SparseSequential(
            post_act_block(64, 128, 3, stride=2, padding=(0, 1, 1), indice_key="spconv4", conv_type="spconv"),
            SparseBasicBlock(128, "res4"), SparseBasicBlock(128, "res4"),
        )
        self.conv_out = spconv.SparseSequential(
            spconv.SparseConv3d(128, 128, (3, 1, 1), stride=(2, 1, 1), bias=False, indice_key="spconv_down2"),
            _bn(128), nn.ReLU(),
        )

    def forward(self, voxel_features, voxel_coords, batch_size, fusion_inputs: Optional[FusionInputs] = None):
        with quiet():  # spconv's own torch.fx message (not part of the swap; see mssf_blocks.integrations.spconv)
            x = spconv.SparseConvTensor(voxel_features, voxel_coords, self.sparse_shape, batch_size)
            x = self.conv_input(x)
            outputs = {}
            for name in ("conv1", "conv2", "conv3", "conv4"):
                stage = getattr(self, name)
                # The one change a fusion backbone needs: fusion stages also receive the camera inputs.
                x = stage(x, fusion_inputs) if isinstance(stage, FusionBlock) else stage(x)
                outputs[name] = x
            outputs["conv_out"] = self.conv_out(x)
        return outputs


# --------------------------------------------------------------------------------------------------
# The swap
# --------------------------------------------------------------------------------------------------
def swap_conv2_for_fusion(backbone: VoxelResBackBone8x) -> FusionBlock:
    """Replace ``backbone.conv2`` by a fusion block built from the stage's own parts."""
    downsample, *residual = list(backbone.conv2)
    backbone.conv2 = FusionBlock(
        MSDFF(FPN_CHANNELS, 32, num_heads=4, num_levels=len(FPN_STRIDES), num_points=4),
        downsample=downsample,  # the stride-2 SparseConv3d block; its stride (2, 2, 2) is read from it
        blocks=spconv.SparseSequential(*residual),
        grid=VoxelGrid(VOXEL_SIZE, POINT_CLOUD_RANGE),  # the input's stride is read from its spatial_shape
        query_init=True,  # the first MSDFF block builds its query (eq. 8) from the fusion's channels and the grid
    )
    return backbone.conv2


# --------------------------------------------------------------------------------------------------
# Random data: radar points, mean-feature voxels, one front camera, FPN features
# --------------------------------------------------------------------------------------------------
def random_frame(batch_size: int = 2, points_per_frame: int = 300, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(POINT_CLOUD_RANGE[3:])
    xyz = lo + torch.rand(batch_size * points_per_frame, 3, generator=gen) * (hi - lo)
    extra = torch.randn(batch_size * points_per_frame, 4, generator=gen)  # RCS, v_r, v_r_comp, time
    points = torch.cat([xyz, extra], dim=1)
    points_batch = torch.arange(batch_size).repeat_interleave(points_per_frame)

    # Mean voxel feature encoder (OpenPCDet's MeanVFE): average the points of every base voxel.
    idx = ((xyz - lo) / torch.tensor(VOXEL_SIZE)).floor().long()
    keys = torch.cat([points_batch[:, None], idx[:, [2, 1, 0]]], dim=1)
    coords, inverse = torch.unique(keys, dim=0, return_inverse=True)
    feats = torch.zeros(coords.shape[0], points.shape[1]).index_add_(0, inverse, points)
    feats = feats / torch.bincount(inverse, minlength=coords.shape[0])[:, None]

    # Front camera looking along +x: camera (right, down, forward) = (-y, -z, x).
    h, w = IMAGE_SIZE
    k = torch.tensor([[128.0, 0, w / 2], [0, 128.0, h / 2], [0, 0, 1]])
    radar_to_cam = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0.3], [1, 0, 0, 0]])
    lidar2img = (k @ radar_to_cam).expand(batch_size, 1, 3, 4).contiguous()
    fpn = [torch.randn(batch_size, 1, FPN_CHANNELS, h // s, w // s, generator=gen) for s in FPN_STRIDES]
    inputs = FusionInputs(fpn, lidar2img, IMAGE_SIZE, points[:, :3], points_batch)
    return feats, coords.int(), inputs


def main(seed: int = 0, num_threads: Optional[int] = 1) -> Dict[str, tuple]:
    """Build, swap, run; print and return ``{stage: (feature shape, grid shape)}``.

    ``num_threads=1`` by default: with these small matrices, extra OpenMP threads only spin (on a
    busy 2-core machine one thread ran this demo 50x faster than two).
    """
    if num_threads is not None:
        previous = torch.get_num_threads()
        torch.set_num_threads(num_threads)
        try:
            return main(seed, None)
        finally:
            torch.set_num_threads(previous)
    torch.manual_seed(seed)
    start = time.perf_counter()
    lo, hi = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(POINT_CLOUD_RANGE[3:])
    grid_size = ((hi - lo) / torch.tensor(VOXEL_SIZE)).round().long().tolist()
    feats, coords, inputs = random_frame(seed=seed)

    backbone = VoxelResBackBone8x(feats.shape[1], grid_size)
    fusion_block = swap_conv2_for_fusion(backbone)
    print(fusion_block)
    backbone.eval()
    with torch.no_grad():
        outputs = backbone(feats, coords, inputs.batch_size, inputs)

    shapes = {"input": (tuple(feats.shape), tuple(backbone.sparse_shape))}
    print(f"input voxels: features {tuple(feats.shape)}, grid {backbone.sparse_shape}")
    for name, t in outputs.items():
        shapes[name] = (tuple(t.features.shape), tuple(t.spatial_shape))
        print(f"{name:>8}: features {tuple(t.features.shape)}, grid {list(t.spatial_shape)}, "
              f"index cache {sorted(t.indice_dict)}")
    print(f"conv2 is a {type(backbone.conv2).__name__} with downsample_stride {fusion_block.downsample_stride}; "
          f"forward took {time.perf_counter() - start:.2f} s")
    return shapes


if __name__ == "__main__":
    main()
