"""VoxelGrid: one grid description (voxel_size + point_cloud_range), and the stride it reads from a sparse
tensor's spatial_shape. References: hand-worked cell counts, and spconv's own output shapes for the
convolution stacks of OpenPCDet's VoxelBackBone8x / VoxelResBackBone8x and VoxelNeXt."""

from __future__ import annotations

import pytest
import torch

from mssf_blocks import SparseVoxels, VoxelGrid
from mssf_blocks.errors import MSSFError

VOD = VoxelGrid(voxel_size=(0.05, 0.05, 0.125), point_cloud_range=(0, -25.6, -3, 51.2, 25.6, 2))


def test_cells_and_corners_hand_worked():
    # x: 51.2 / 0.05 = 1024, y: 51.2 / 0.05 = 1024, z: 5 / 0.125 = 40
    assert VOD.spatial_shape == (40, 1024, 1024)
    assert VOD.grid_size == (1024, 1024, 40)
    assert VOD.point_range_min == (0.0, -25.6, -3.0) and VOD.point_range_max == (51.2, 25.6, 2.0)
    kitti = VoxelGrid((0.05, 0.05, 0.1), (0, -40, -3, 70.4, 40, 1))
    assert kitti.spatial_shape == (40, 1600, 1408)  # OpenPCDet's KITTI grid_size (1408, 1600, 40)


def test_voxel_centres_hand_worked():
    coords = torch.tensor([[0, 0, 0, 0], [1, 3, 2, 1]], dtype=torch.int32)
    # stride 2: (index + 0.5) * voxel * 2 + min
    want = torch.tensor([[0.05, -25.55, -2.875], [0.15, -25.35, -2.125]], dtype=torch.float64)
    torch.testing.assert_close(VOD.voxel_centers(coords, (2, 2, 2), dtype=torch.float64), want)


def _spconv_shapes(stack, shape):
    """Shapes spconv itself gives after each convolution of ``stack`` (kernel, stride, padding per axis)."""
    spconv = pytest.importorskip("spconv.pytorch")
    from mssf_blocks.integrations.spconv import quiet

    out = []
    coords = torch.tensor([[0, 0, 0, 0]], dtype=torch.int32)
    x = spconv.SparseConvTensor(torch.ones(1, 1), coords, list(shape), 1)
    with quiet():
        for k, s, p in stack:
            x = spconv.SparseConv3d(1, 1, k, stride=s, padding=p, bias=False)(x)
            out.append(tuple(int(v) for v in x.spatial_shape))
    return out


def test_stride_of_openpcdet_voxel_backbone_8x():
    # OpenPCDet's sparse_shape is grid_size[::-1] + [1, 0, 0]: one z cell more than the grid
    sparse_shape = (41, 1024, 1024)
    stack = [(3, 2, 1), (3, 2, 1), (3, 2, (0, 1, 1))]  # conv2, conv3, conv4 (VoxelBackBone8x / VoxelResBackBone8x)
    shapes = _spconv_shapes(stack, sparse_shape)
    assert VOD.stride_of(sparse_shape) == (1, 1, 1)
    assert [VOD.stride_of(s) for s in shapes] == [(2, 2, 2), (4, 4, 4), (8, 8, 8)]


def test_stride_of_voxelnext_stages_and_the_readme_shape():
    stack = [(3, 2, 1)] * 5  # VoxelNeXt conv2 .. conv6: strides 2 .. 32, padding 1
    shapes = _spconv_shapes(stack, (41, 1024, 1024))
    assert [VOD.stride_of(s) for s in shapes] == [(2, 2, 2), (4, 4, 4), (8, 8, 8), (16, 16, 16), (32, 32, 32)]
    assert VOD.stride_of((40, 1024, 1024)) == (1, 1, 1)  # the README's tensor: the grid's own shape


def test_a_z_only_stride_is_read_per_axis():
    shapes = _spconv_shapes([(3, 2, 1), (3, (2, 1, 1), (0, 1, 1))], (41, 1024, 1024))
    assert VOD.stride_of(shapes[1]) == (4, 2, 2)


def test_a_shape_of_another_grid_is_refused_naming_both_shapes():
    with pytest.raises(MSSFError, match=r"x\.spatial_shape: expected .*\(40, 1024, 1024\) at stride 1.*got \(41, 1600, 1408\)"):
        VOD.stride_of((41, 1600, 1408))  # KITTI's sparse shape on the VoD grid


def test_a_permuted_shape_is_named():
    with pytest.raises(MSSFError, match=r"got \(1024, 1024, 40\).*\(40, 1024, 1024\) would fit.*another order"):
        VOD.stride_of((1024, 1024, 40))


def test_an_axis_no_other_axis_decides_is_refused():
    tiny = VoxelGrid((1.0, 1.0, 1.0), (0, 0, 0, 1, 1, 1))  # one cell per axis: every stride gives 1
    with pytest.raises(MSSFError, match=r"fits strides \[1, 2, 4.*SparseVoxels\(\.\.\., grid=grid, stride="):
        tiny.stride_of((1, 1, 1))
    flat = VoxelGrid((1.0, 1.0, 4.0), (0, 0, 0, 64, 64, 4))  # a one-cell z axis takes the x / y stride
    assert flat.stride_of((1, 16, 16)) == (4, 4, 4)


@pytest.mark.parametrize("kwargs, message", [
    (dict(voxel_size=(0.05, 0.05), point_cloud_range=(0, 0, 0, 1, 1, 1)), r"voxel_size: expected 3"),
    (dict(voxel_size=(0.05, 0.05, -1), point_cloud_range=(0, 0, 0, 1, 1, 1)), r"voxel_size: expected 3 positive"),
    (dict(voxel_size=(0.1, 0.1, 0.1), point_cloud_range=(0, 0, 0, 1, 1)), r"point_cloud_range: expected 6"),
    (dict(voxel_size=(0.1, 0.1, 0.1), point_cloud_range=(1, 0, 0, 0, 1, 1)), r"max > min"),
    (dict(voxel_size=(0.3, 0.1, 0.1), point_cloud_range=(0, 0, 0, 1, 1, 1)), r"along x.*3\.3333 cells"),
])
def test_bad_grids_are_refused_naming_the_argument(kwargs, message):
    with pytest.raises(MSSFError, match=message):
        VoxelGrid(**kwargs)


def test_sparse_voxels_grid_and_loose_forms_agree():
    coords = torch.tensor([[0, 1, 2, 3]], dtype=torch.int32)
    on_grid = SparseVoxels(torch.ones(1, 2), coords, (21, 512, 512), 1, grid=VOD)  # stride read from the shape
    loose = SparseVoxels(torch.ones(1, 2), coords, (21, 512, 512), 1, voxel_size=VOD.voxel_size,
                         point_range_min=VOD.point_range_min, stride=(2, 2, 2))
    assert on_grid.stride == loose.stride == (2, 2, 2)
    assert on_grid.voxel_size == loose.voxel_size and on_grid.point_range_min == loose.point_range_min
    torch.testing.assert_close(on_grid.voxel_centers(), loose.voxel_centers())
    # the loose form spans what the tensor covers: min + shape * stride * voxel
    assert loose.grid.point_range_max == pytest.approx((51.2, 25.6, 2.25))
    with pytest.raises(MSSFError, match=r"grid: expected a VoxelGrid, got tuple"):
        SparseVoxels(torch.ones(1, 2), coords, (21, 512, 512), 1, (0.05, 0.05, 0.125), (0, -25.6, -3))
    with pytest.raises(MSSFError, match=r"either grid= or voxel_size="):
        SparseVoxels(torch.ones(1, 2), coords, (21, 512, 512), 1, grid=VOD, voxel_size=(0.05, 0.05, 0.125))


def test_modules_take_the_grid_or_its_loose_value_not_both():
    from mssf_blocks import QueryInit, VoxelCentroidProjector

    assert VoxelCentroidProjector(grid=VOD).point_range_max == VOD.point_range_max
    assert QueryInit(4, 4, 4, grid=VOD).point_cloud_range == QueryInit(4, 4, 4, VOD).point_cloud_range == VOD.point_cloud_range
    with pytest.raises(MSSFError, match=r"point_range_max: expected either grid= or point_range_max="):
        VoxelCentroidProjector(point_range_max=(1.0, 1.0, 1.0), grid=VOD)
    with pytest.raises(MSSFError, match=r"point_cloud_range: expected either grid= or point_cloud_range="):
        QueryInit(4, 4, 4, (0, 0, 0, 1, 1, 1), grid=VOD)
    with pytest.raises(MSSFError, match=r"grid: expected a VoxelGrid, got tuple"):
        VoxelCentroidProjector(grid=(0.05, 0.05, 0.125))
