"""Issue 42: block-level geometry mistakes on a coarse grid, named on the first call (no warm-up).

A generated VoD-like scene (``mssf_examples.scenes.synthetic``: VoD's camera, 5 accumulated scans, three times the
default point count: ~550 points, more than a real VoD frame's ~340) voxelised on a coarse grid
(0.2 / 0.2 / 0.25 m), where a wrong grid still leaves some voxels holding points by chance, so the zero
checks of ``_sanity`` say nothing and a fresh projector has no running value. Each mistake below must be
named by a fresh projector / block on its first call; the correct inputs must be quiet.
"""

from __future__ import annotations

import math
import warnings

import pytest
import torch

from mssf_blocks import SparseVoxels, VoxelCentroidProjector
from mssf_blocks.errors import MSSFError, MSSFGeometryWarning
from mssf_blocks.geometry import augmentation_matrix

pytestmark = pytest.mark.usefixtures("one_thread")

COARSE = (0.2, 0.2, 0.25)  # (x, y, z)
RANGE = (0.0, -12.8, -3.0, 25.6, 12.8, 2.0)  # the generator's default
SHAPE = (20, 128, 128)  # (D, H, W)


def scene_points(seed: int = 0):
    """``(points (P, 3), lidar2img (1, 3, 4), image_size)`` of a generated scene."""
    from mssf_examples.scenes.synthetic import SceneConfig, generate_scene

    s = generate_scene(seed, SceneConfig(point_cloud_range=RANGE, points_scale=3.0))
    return s.points[:, :3].contiguous(), s.lidar2img.float()[None], s.image_size


def voxelize(points: torch.Tensor, points_batch: torch.Tensor, batch_size: int = 1) -> SparseVoxels:
    """The voxels holding the points (on the grid), coords ``(batch, z, y, x)``."""
    lo, hi = torch.tensor(RANGE[:3]), torch.tensor(RANGE[3:])
    keep = ((points >= lo) & (points < hi)).all(1)
    idx = ((points[keep].double() - lo.double()) / torch.tensor(COARSE, dtype=torch.float64)).floor().long()
    rows = torch.cat([points_batch[keep, None], idx[:, [2, 1, 0]]], 1)
    coords = torch.unique(rows, dim=0).int()
    return SparseVoxels(torch.zeros(len(coords), 4), coords, SHAPE, batch_size, voxel_size=COARSE, point_range_min=RANGE[:3])


def scene(seed: int = 0):
    pts, l2i, size = scene_points(seed)
    pb = torch.zeros(len(pts), dtype=torch.long)
    return voxelize(pts, pb), pts, pb, l2i, size


def project(vox, pts, pb, l2i, size, pts2s=None):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        out = VoxelCentroidProjector()(vox, pts, pb, l2i, size, pts2s)
    return out, [str(w.message) for w in got if issubclass(w.category, MSSFGeometryWarning)]


def _zero_checks_silent(out) -> None:
    """The mistake leaves some voxels holding points and some in view: the old zero checks are silent."""
    assert out.has_points.any() and out.valid.any()


def test_correct_coarse_scene_is_quiet_at_every_stride():
    spconv = pytest.importorskip("spconv.pytorch")
    for seed in range(3):
        vox, pts, pb, l2i, size = scene(seed)
        out, msgs = project(vox, pts, pb, l2i, size)
        assert msgs == [] and out.has_points.all()
        t = vox.to_spconv()
        for k in range(2):  # the voxels of SparseConv3d(kernel 3, stride 2, padding 1), as backbones build them
            t = spconv.SparseConv3d(4, 4, 3, 2, 1)(t)
            down = SparseVoxels.from_spconv(t, voxel_size=COARSE, point_range_min=RANGE[:3], stride=(2 ** (k + 1),) * 3)
            assert project(down, pts, pb, l2i, size)[1] == []


def test_correct_augmented_batch_of_two_is_quiet():
    (v0, p0, b0, l0, size), (_, p1, _, l1, _) = scene(1), scene(2)
    aug = augmentation_matrix(flip_x=True, rotation=0.7, scale=1.05)
    p1 = (torch.cat([p1, torch.ones(len(p1), 1)], 1) @ aug.float().T)[:, :3]
    pts, pb = torch.cat([p0, p1]), torch.cat([b0, torch.ones(len(p1), dtype=torch.long)])
    p2s = torch.stack([torch.eye(4), torch.linalg.inv(aug).float()])
    out, msgs = project(voxelize(pts, pb, 2), pts, pb, torch.cat([l0, l1]), size, p2s)
    assert msgs == [] and out.has_points.all()


def test_voxel_size_in_zyx_order_is_named_on_the_first_call():
    vox, pts, pb, l2i, size = scene()
    wrong = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=COARSE[::-1], point_range_min=RANGE[:3])
    out, msgs = project(wrong, pts, pb, l2i, size)
    _zero_checks_silent(out)
    assert any(m.startswith("points: only") and "voxel_size (x, y, z order)" in m for m in msgs), msgs


def test_point_range_min_a_voxel_off_is_named_on_the_first_call():
    vox, pts, pb, l2i, size = scene()
    wrong = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=COARSE, point_range_min=(RANGE[0], RANGE[1] + COARSE[1], RANGE[2]))
    out, msgs = project(wrong, pts, pb, l2i, size)
    _zero_checks_silent(out)
    assert any(m.startswith("points: only") and "point_range_min" in m for m in msgs), msgs


def test_coords_in_bxyz_order_with_the_matching_shape_is_named():
    vox, pts, pb, l2i, size = scene()
    # an OpenPCDet-style grid_size (X, Y, Z) used as spatial_shape, and (batch, x, y, z) coords: in range
    wrong = SparseVoxels(vox.features, vox.coords[:, [0, 3, 2, 1]].contiguous(), SHAPE[::-1], 1, voxel_size=COARSE, point_range_min=RANGE[:3])
    out, msgs = project(wrong, pts, pb, l2i, size)
    _zero_checks_silent(out)
    assert any("coords order (batch, z, y, x)" in m for m in msgs), msgs


def _block(downsample_stride=None, grid=None):
    spconv = pytest.importorskip("spconv.pytorch")
    from mssf_blocks import FusionBlock, VoxelGrid
    from mssf_blocks.samplers import SFF

    torch.manual_seed(0)
    down = spconv.SparseSequential(spconv.SparseConv3d(4, 8, 3, 2, 1, bias=False))
    return FusionBlock(SFF([3], 8), grid=grid or VoxelGrid(COARSE, RANGE), downsample=down,
                       downsample_stride=downsample_stride).eval()


def _run_block(block, x, inputs):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        with torch.no_grad():
            block(x, inputs)
    return [str(w.message) for w in got if issubclass(w.category, MSSFGeometryWarning)]


def test_a_block_grid_that_is_not_the_voxels_grid_is_refused_naming_both_shapes():
    # (The mistake this replaces, a block's output stride given as its in_stride, cannot be made any more: the
    # stride of an spconv input is read from its spatial_shape against the block's grid.)
    spconv = pytest.importorskip("spconv.pytorch")
    from mssf_blocks import VoxelGrid
    from mssf_blocks.samplers import FusionInputs

    vox, pts, pb, l2i, size = scene()
    inputs = FusionInputs([torch.zeros(1, 3, size[0] // 4, size[1] // 4)], l2i, size, pts, pb)
    torch.manual_seed(0)
    x = spconv.SparseConv3d(4, 4, 3, 2, 1)(vox.to_spconv())  # the second block's input, at stride 2
    assert tuple(x.spatial_shape) == (10, 64, 64)
    assert _run_block(_block(), x, inputs) == []
    kitti = VoxelGrid(COARSE, (0.0, -40.0, -3.0, 70.4, 40.0, 1.0))  # another dataset's range: (16, 400, 352) cells
    with pytest.raises(MSSFError, match=r"x\.spatial_shape: expected .*\(16, 400, 352\) at stride 1.*got \(10, 64, 64\)"):
        _block(grid=kitti)(x, inputs)


def test_downsample_stride_that_contradicts_the_convolution_is_refused():
    _block(downsample_stride=(2, 2, 2))  # agrees: accepted
    with pytest.raises(MSSFError, match=r"downsample_stride: expected \(2, 2, 2\).*got \(1, 2, 2\)"):
        _block(downsample_stride=(1, 2, 2))


def test_image_size_twice_the_projection_image_is_named_on_a_coarse_grid():
    vox, pts, pb, l2i, size = scene()
    out, msgs = project(vox, pts, pb, l2i, (2 * size[0], 2 * size[1]))
    assert not any("top-left quarter" in m for m in project(vox, pts, pb, l2i, size)[1])
    assert any("top-left quarter" in m and "twice" in m and "raw points" in m for m in msgs), msgs


def test_forward_augmentation_as_points_to_sensor_is_named_on_the_first_call():
    vox, pts, pb, l2i, size = scene()
    aug = augmentation_matrix(rotation=0.3).float()  # doubled: 0.87 -> 0.49 of the voxels in view
    pts_aug = (torch.cat([pts, torch.ones(len(pts), 1)], 1) @ aug.T)[:, :3]
    lo = torch.tensor(RANGE[:3])
    keep = (pts_aug >= lo).all(1) & (pts_aug < torch.tensor(RANGE[3:])).all(1)
    pts_aug, pb = pts_aug[keep], pb[keep]
    vox = voxelize(pts_aug, pb)
    out, msgs = project(vox, pts_aug, pb, l2i, size, torch.linalg.inv(aug)[None])
    assert msgs == [], msgs
    right = out.valid.float().mean().item()
    out, msgs = project(vox, pts_aug, pb, l2i, size, aug[None])
    wrong = out.valid.float().mean().item()
    assert 0.25 * right < wrong < right  # above the old collapse threshold; no warm-up anyway
    assert any(m.startswith("points_to_sensor:") and "its inverse" in m and "forward augmentation" in m
               for m in msgs), msgs


def test_points_batch_all_zero_for_a_batch_of_two_is_named():
    (v0, p0, b0, l0, size), (v1, p1, b1, l1, _) = scene(1), scene(2)
    pts = torch.cat([p0, p1])
    right = torch.cat([b0, b1 + 1])
    vox = voxelize(pts, right, 2)
    assert project(vox, pts, right, torch.cat([l0, l1]), size)[1] == []
    _, msgs = project(vox, pts, torch.zeros_like(right), torch.cat([l0, l1]), size)
    assert any(m.startswith("points_batch: sample 1 has") for m in msgs), msgs


@pytest.mark.parametrize("rotation", [45.0, -90, 7.0])
def test_rotation_in_degrees_is_refused_by_the_builders(rotation):
    with pytest.raises(MSSFError, match=r"rotation: .*degrees\? pass radians"):
        augmentation_matrix(rotation=rotation)
    augmentation_matrix(rotation=math.radians(rotation))
    augmentation_matrix(rotation=2 * math.pi)  # a full turn is still radians
    from mssf_examples.data.augment import AugmentationConfig

    with pytest.raises(MSSFError, match=r"rotation_range: .*degrees\? pass radians"):
        AugmentationConfig(rotation_range=(-abs(rotation), abs(rotation)))


def test_first_call_checks_are_gated_like_the_coverage_checks():
    """They read data: off with set_geometry_checks(False) (the default on an accelerator) and while tracing."""
    from mssf_blocks.checks import set_geometry_checks

    vox, pts, pb, l2i, size = scene()
    wrong = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=COARSE[::-1], point_range_min=RANGE[:3])
    assert project(wrong, pts, pb, l2i, size)[1]
    set_geometry_checks(False)
    try:
        assert project(wrong, pts, pb, l2i, size)[1] == []
    finally:
        set_geometry_checks(None)
    from unittest import mock

    with mock.patch("mssf_blocks.checks.geometry.is_tracing", return_value=True):
        assert project(wrong, pts, pb, l2i, size)[1] == []


def test_image_size_half_the_projection_image_is_named_not_as_swapped():
    vox, pts, pb, l2i, size = scene()
    msgs = project(vox, pts, pb, l2i, (size[0] // 2, size[1] // 2))[1]
    assert any("is image_size smaller than the image lidar2img projects into" in m for m in msgs), msgs
    assert not any("swapped" in m for m in msgs), msgs
    assert any("swapped" in m for m in project(vox, pts, pb, l2i, size[::-1])[1])  # a real swap still is


@pytest.mark.parametrize("mistake", ["point_range_min_zyx", "points_of_another_frame", "voxel_size_halved"])
def test_other_grid_mistakes_of_the_class_are_named(mistake):
    """Not only the listed instances: whatever makes the voxels and the points disagree."""
    vox, pts, pb, l2i, size = scene()
    if mistake == "point_range_min_zyx":
        vox = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=COARSE, point_range_min=RANGE[:3][::-1])
    elif mistake == "points_of_another_frame":
        pts = scene_points(seed=7)[0]
        pb = torch.zeros(len(pts), dtype=torch.long)
    else:  # the base grid's voxel size for voxels of a grid twice as fine (or a pillar size mix-up)
        vox = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=tuple(v / 2 for v in COARSE), point_range_min=RANGE[:3])
    _, msgs = project(vox, pts, pb, l2i, size)
    assert any(m.startswith(("points: only", "centroids: none")) for m in msgs), msgs
