"""The README's drop-in example (``FusionBlock(MSDFF(256, 32), grid, query_init=True)``) as a benchmark frame.

The fusion step of README.md's "Drop it into your detector" at its widths and geometry: 256-channel FPN
levels at strides 4-32 of a 320 x 512 image, two samples, its camera (focal 200 px, looking along +x), its
grid (0.05 x 0.05 x 0.125 m over (0, -25.6, -3) - (51.2, 25.6, 2)), voxels with 32 channels drawn in its
point box (x 5-30 m, y -5-5 m, z -2.5-0.5 m: every voxel in the image). The stage's spconv downsample and
residual blocks are left out: they are the same in eager and compiled runs (spconv is not captured by
``torch.compile``), so the fusion block is what compiling can change. Three points per voxel, inside it (the
README draws one per voxel; equal point and voxel counts would make dynamo's duck sizing share their symbol
and recompile at the first frame where they differ).
"""

from __future__ import annotations

import torch

from mssf_blocks import MSDFF, FusionBlock, FusionInputs, SparseVoxels, VoxelGrid

GRID = VoxelGrid(voxel_size=(0.05, 0.05, 0.125), point_cloud_range=(0, -25.6, -3, 51.2, 25.6, 2))
B, H, W = 2, 320, 512
POINTS_PER_VOXEL = 3


def build() -> FusionBlock:
    return FusionBlock(MSDFF(256, 32), GRID, query_init=True)


def frame(n: int, seed: int):
    """``(voxels, inputs, None)``: ``n`` distinct voxels (about ``n / B`` per sample) and the README's inputs."""
    g = torch.Generator().manual_seed(seed)
    lo, size = torch.tensor(GRID.point_range_min), torch.tensor(GRID.voxel_size)
    box_lo, box = torch.tensor([5.0, -5.0, -2.5]), torch.tensor([25.0, 10.0, 3.0])
    cells = ((torch.rand(2 * n, 3, generator=g) * box + box_lo - lo) / size).floor()  # x, y, z
    batch = torch.randint(0, B, (2 * n, 1), generator=g).float()
    coords = torch.unique(torch.cat([batch, cells.flip(1)], 1), dim=0)  # (b, z, y, x), sorted
    coords = coords[torch.randperm(len(coords), generator=g)[:n]].int()
    vox = SparseVoxels(torch.randn(n, 32, generator=g), coords, grid=GRID, batch_size=B)
    inside = torch.rand(POINTS_PER_VOXEL * n, 3, generator=g)
    rows = torch.arange(n).repeat(POINTS_PER_VOXEL)
    xyz = lo + (coords[rows][:, 1:].flip(1).float() + inside) * size
    fpn = [torch.randn(B, 256, H // s, W // s, generator=g) for s in (4, 8, 16, 32)]
    k = torch.tensor([[200.0, 0, W / 2], [0, 200, H / 2], [0, 0, 1]])
    lidar2img = (k @ torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])).expand(B, 1, 3, 4)
    inputs = FusionInputs(image_features=fpn, lidar2img=lidar2img, image_size=(H, W), points=xyz,
                          points_batch=coords[rows, 0].long())
    return vox, inputs, None
