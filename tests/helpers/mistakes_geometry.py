"""Cases of the "Common mistakes" table (tests/docs/test_docs_mistakes_table.py): geometry and grid mistakes.

Scenes: test_first_call's coarse-grid generated scene (``fc``), test_geometry_sanity's cone of points
in front of a VoD-like camera (``gs``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

# the scenes are those of the test modules in tests/checks
if str(Path(__file__).resolve().parents[1] / "checks") not in sys.path:
    sys.path.append(str(Path(__file__).resolve().parents[1] / "checks"))
import test_first_call as fc  # noqa: E402
import test_geometry_sanity as gs  # noqa: E402
from mistakes_registry import case, outcome  # noqa: E402


def _coarse():
    return fc.scene()


@case("`image_size` larger than the image")
def _():
    vox, pts, pb, l2i, size = _coarse()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, (2 * size[0], 2 * size[1])))


@case("`image_size` smaller than the image")
def _():
    vox, pts, pb, l2i, size = _coarse()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, (size[0] // 2, size[1] // 2)))


@case("image and levels resized, `lidar2img` not")
def _():
    vox, pts, pb, l2i = gs.scene()
    half = [torch.zeros(1, 4, 60, 80)]
    from mssf_blocks.samplers import FusionInputs

    def run():  # the image and its level resized to half, lidar2img kept: image_size is the new size
        FusionInputs(half, l2i, (240, 320), pts, pb)
        shifted = l2i.clone()
        shifted[:, :2] += 5000 * shifted[:, 2:3]
        fc.VoxelCentroidProjector()(vox, pts, pb, shifted, (240, 320))
    return outcome(run)


@case("`image_size` as `(W, H)` with levels")
def _():
    return outcome(lambda: gs._inputs([torch.zeros(1, 4, 120, 160)], size=gs.HW[::-1]))


@case("`image_size` as `(W, H)` to the projector alone")
def _():
    vox, pts, pb, l2i = gs.scene()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, gs.HW[::-1]))


@case("FPN levels coarsest first")
def _():
    return outcome(lambda: gs._inputs([torch.zeros(1, 4, 60, 80), torch.zeros(1, 4, 120, 160)]))


@case("a level not `image_size` over a stride")
def _():
    return outcome(lambda: gs._inputs([torch.zeros(1, 4, 120, 160), torch.zeros(1, 4, 60, 60)]))


@case("channels-last (NHWC) levels")
def _():
    return outcome(lambda: gs._inputs([torch.zeros(1, 120, 160, 4)]))


@case("`lidar2img` a 4x4 lidar-to-camera transform")
def _():
    vox, pts, pb, _ = gs.scene()
    _, rt = gs.camera()
    rigid = torch.cat([rt, torch.tensor([[0.0, 0, 0, 1]], dtype=torch.float64)]).float()[None]
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, rigid, gs.HW))


@case("`lidar2img` the intrinsics alone")
def _():
    vox, pts, pb, _ = gs.scene()
    k, _ = gs.camera()
    kk = torch.cat([k, torch.zeros(3, 1, dtype=torch.float64)], 1).float()[None]
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, kk, gs.HW))


@case("the forward augmentation matrix as `points_to_sensor`")
def _():
    _, pts, pb, l2i, size = _coarse()
    aug = fc.augmentation_matrix(rotation=0.3).float()
    pts = (torch.cat([pts, torch.ones(len(pts), 1)], 1) @ aug.T)[:, :3]
    keep = (pts >= torch.tensor(fc.RANGE[:3])).all(1) & (pts < torch.tensor(fc.RANGE[3:])).all(1)
    pts, pb = pts[keep], pb[keep]
    return outcome(lambda: fc.VoxelCentroidProjector()(fc.voxelize(pts, pb), pts, pb, l2i, size, aug[None]))


@case("`voxel_size` in `(z, y, x)` order, a wrong voxels' `stride` or `point_range_min`")
def _():
    vox, pts, pb, l2i, size = _coarse()
    coarse = fc.SparseVoxels(vox.features, vox.coords, fc.SHAPE, 1, voxel_size=fc.COARSE[::-1], point_range_min=fc.RANGE[:3])
    fine, fpts, fpb, fl2i = gs.scene()  # a scene where no voxel holds a point
    zero = fc.SparseVoxels(fine.features, fine.coords, gs.SHAPE, 1, voxel_size=gs.VOXEL[::-1], point_range_min=gs.LO)
    return outcome(lambda: fc.VoxelCentroidProjector()(coarse, pts, pb, l2i, size),
                   lambda: fc.VoxelCentroidProjector()(zero, fpts, fpb, fl2i, gs.HW))


@case("a `FusionBlock` built with another grid than its voxels'")
def _():
    spconv = pytest.importorskip("spconv.pytorch")
    from mssf_blocks.samplers import FusionInputs

    vox, pts, pb, l2i, size = _coarse()
    inputs = FusionInputs([torch.zeros(1, 3, size[0] // 4, size[1] // 4)], l2i, size, pts, pb)
    torch.manual_seed(0)
    x = spconv.SparseConv3d(4, 4, 3, 2, 1)(vox.to_spconv())
    from mssf_blocks import VoxelGrid

    kitti = VoxelGrid(fc.COARSE, (0.0, -40.0, -3.0, 70.4, 40.0, 1.0))
    return outcome(lambda: fc._block(grid=kitti)(x, inputs))


@case("coords in `(batch, x, y, z)` order")
def _():
    vox, pts, pb, l2i, size = _coarse()
    wrong = fc.SparseVoxels(vox.features, vox.coords[:, [0, 3, 2, 1]].contiguous(), fc.SHAPE[::-1], 1, voxel_size=fc.COARSE,
                            point_range_min=fc.RANGE[:3])
    return outcome(lambda: fc.VoxelCentroidProjector()(wrong, pts, pb, l2i, size))


@case("`spatial_shape` in `(W, H, D)` order")
def _():
    spconv = pytest.importorskip("spconv.pytorch")
    import test_spconv_inputs as si
    from mssf_blocks import SparseVoxels
    from mssf_blocks.samplers import FusionInputs

    # a 1.6 x 0.8 x 0.8 m range over voxels (0.1, 0.1, 0.2): (D, H, W) = (4, 8, 16); (16, 8, 4) given
    grid = dict(voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))
    inputs = FusionInputs([torch.zeros(1, 4, 8, 8)], torch.eye(3, 4)[None], (8, 8), torch.zeros(0, 3),
                          torch.zeros(0, dtype=torch.long))
    idx = torch.tensor([[0, 1, 2, 12], [0, 3, 7, 15]], dtype=torch.int32)  # x up to 15
    small = torch.tensor([[0, 1, 2, 3]], dtype=torch.int32)  # inside both shapes: only the metric extent tells
    return outcome(lambda: SparseVoxels(torch.ones(2, 4), idx, (16, 8, 4), 1, **grid),
                   lambda: si._block()(spconv.SparseConvTensor(torch.ones(2, 4), idx, [16, 8, 4], 1), inputs),
                   lambda: si._block((1.6, 0.8, 0.8))(SparseVoxels(torch.ones(1, 4), small, (16, 8, 4), 1, **grid),
                                                      inputs))


@case("`downsample_stride` that contradicts")
def _():
    return outcome(lambda: fc._block(downsample_stride=(1, 2, 2)))


@case("a rotation in degrees")
def _():
    from mssf_examples.data.augment import AugmentationConfig

    return outcome(lambda: fc.augmentation_matrix(rotation=45.0),
                   lambda: AugmentationConfig(rotation_range=(-45.0, 45.0)))


@case("`points_batch` labelling one sample's points as another's")
def _():
    (_, p0, b0, l0, size), (_, p1, b1, l1, _) = fc.scene(1), fc.scene(2)
    pts = torch.cat([p0, p1])
    vox = fc.voxelize(pts, torch.cat([b0, b1 + 1]), 2)
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, torch.zeros(len(pts), dtype=torch.long),
                                                        torch.cat([l0, l1]), size))


@case("an empty point list with voxels")
def _():
    vox, pts, pb, l2i = gs.scene()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts[:0], pb[:0], l2i, gs.HW))
