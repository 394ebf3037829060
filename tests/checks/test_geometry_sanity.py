"""Issue 33, item 1: geometry misuse that used to pass silently is named where the inputs enter.

The scene is built here from first principles: a VoD-like camera ``K @ [R | t]`` (camera right, down,
forward = -y, -z, x), points in front of it, the voxels that hold them. Each misuse below is one a user
makes with real data; the test asserts the named error or warning, and that the correct use is quiet.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from mssf_blocks import SparseVoxels, VoxelCentroidProjector
from mssf_blocks.checks.geometry import set_geometry_checks
from mssf_blocks.errors import MSSFError, MSSFGeometryWarning
from mssf_blocks.samplers import FusionInputs
from mssf_blocks.geometry import augmentation_matrix

pytestmark = pytest.mark.usefixtures("one_thread")

HW = (480, 640)
VOXEL = (0.5, 0.25, 0.2)  # (x, y, z), deliberately not cubic: a (z, y, x) order is a different grid
LO = (0.0, -30.0, -3.0)
SHAPE = (30, 240, 100)  # (D, H, W) = z, y, x cells


def camera():
    k = torch.tensor([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], dtype=torch.float64)
    rt = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0.5], [1, 0, 0, 1.0]], dtype=torch.float64)
    return k, rt


def scene(n=300, seed=0):
    """Points in a 60-degree cone in front of the camera (the image's width), 5-45 m; their voxels."""
    g = torch.Generator().manual_seed(seed)
    x = 5 + 40 * torch.rand(n, generator=g, dtype=torch.float64)
    y = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 1.2 * x
    z = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2.0
    pts = torch.stack([x, y, z], 1).float()
    idx = ((pts.double() - torch.tensor(LO, dtype=torch.float64)) / torch.tensor(VOXEL, dtype=torch.float64)).floor().long()
    cells = torch.unique(torch.stack([idx[:, 2], idx[:, 1], idx[:, 0]], 1), dim=0)
    coords = torch.cat([torch.zeros(len(cells), 1, dtype=torch.long), cells], 1).int()
    vox = SparseVoxels(torch.zeros(len(cells), 4), coords, SHAPE, 1, voxel_size=VOXEL, point_range_min=LO)
    k, rt = camera()
    return vox, pts, torch.zeros(n, dtype=torch.long), (k @ rt).float()[None]


def project(vox, pts, pb, l2i, size=HW, pts2s=None):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        out = VoxelCentroidProjector()(vox, pts, pb, l2i, size, pts2s)
    return out, [str(w.message) for w in got if issubclass(w.category, MSSFGeometryWarning)]


def test_correct_geometry_is_quiet_and_mostly_in_image():
    vox, pts, pb, l2i = scene()
    out, msgs = project(vox, pts, pb, l2i)
    assert msgs == []
    assert out.valid.float().mean() > 0.9 and out.has_points.all()


def test_image_size_twice_the_real_size_warns_top_left_quarter():
    vox, pts, pb, l2i = scene()
    _, msgs = project(vox, pts, pb, l2i, (2 * HW[0], 2 * HW[1]))
    assert any("top-left quarter" in m and "twice" in m for m in msgs), msgs


def test_swapped_image_size_in_the_projector_warns():
    vox, pts, pb, l2i = scene()
    _, msgs = project(vox, pts, pb, l2i, (HW[1], HW[0]))
    assert any("swapped" in m for m in msgs), msgs


def test_resized_image_without_lidar2img_warns_no_voxel_in_image():
    vox, pts, pb, l2i = scene()
    shifted = l2i.clone()
    shifted[:, :2] += 5000 * shifted[:, 2:3]  # the principal point of another image: nothing lands inside
    _, msgs = project(vox, pts, pb, shifted)
    assert any("none of sample 0" in m and "image_size" in m and "points_to_sensor" in m for m in msgs), msgs


def test_rigid_transform_as_lidar2img_is_named():
    vox, pts, pb, _ = scene()
    _, rt = camera()
    rigid = torch.cat([rt, torch.tensor([[0.0, 0, 0, 1]], dtype=torch.float64)]).float()[None]  # 4x4
    _, msgs = project(vox, pts, pb, rigid)
    assert any("rigid" in m for m in msgs), msgs


def test_intrinsics_alone_as_lidar2img_is_named():
    vox, pts, pb, _ = scene()
    k, _ = camera()
    kk = torch.cat([k, torch.zeros(3, 1, dtype=torch.float64)], 1).float()[None]
    _, msgs = project(vox, pts, pb, kk)
    assert any("intrinsics alone" in m for m in msgs), msgs


def test_forward_augmentation_as_points_to_sensor_warns():
    vox, pts, pb, l2i = scene()
    # the augmented scene: rotated by 1.2 rad; passing the forward matrix again instead of its inverse
    # turns the centroids by 2.4 rad, away from the camera
    aug = augmentation_matrix(rotation=1.2).float()
    pts_aug = (torch.cat([pts, torch.ones(len(pts), 1)], 1) @ aug.T)[:, :3]
    idx = ((pts_aug.double() - torch.tensor((-50.0, -50.0, -3.0), dtype=torch.float64))
           / torch.tensor(VOXEL, dtype=torch.float64)).floor().long()
    cells = torch.unique(torch.stack([idx[:, 2], idx[:, 1], idx[:, 0]], 1), dim=0)
    coords = torch.cat([torch.zeros(len(cells), 1, dtype=torch.long), cells], 1).int()
    vox = SparseVoxels(torch.zeros(len(cells), 4), coords, (30, 480, 200), 1, voxel_size=VOXEL, point_range_min=(-50.0, -50.0, -3.0))
    out, msgs = project(vox, pts_aug, pb, l2i, pts2s=torch.linalg.inv(aug)[None])
    assert msgs == [] and out.valid.float().mean() > 0.9
    _, msgs = project(vox, pts_aug, pb, l2i, pts2s=aug[None])
    assert any("none of sample 0" in m and "points_to_sensor" in m for m in msgs), msgs


def test_voxel_size_in_zyx_order_warns_no_centroid():
    vox, pts, pb, l2i = scene()
    wrong = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=VOXEL[::-1], point_range_min=LO)
    _, msgs = project(wrong, pts, pb, l2i)
    assert any("centroids" in m and "voxel_size" in m for m in msgs), msgs


def test_wrong_point_range_min_and_stride_warn_no_centroid():
    vox, pts, pb, l2i = scene()
    for wrong in (SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=VOXEL, point_range_min=(0.0, 0.0, 0.0)),
                  SparseVoxels(vox.features, vox.coords // torch.tensor([1, 8, 8, 8], dtype=torch.int32),
                               (4, 30, 13), 1, voxel_size=VOXEL, point_range_min=LO)):  # stride-8 coordinates declared as stride 1
        _, msgs = project(wrong, pts, pb, l2i)
        assert any("centroids" in m and "the voxels' stride" in m for m in msgs), msgs


def test_empty_point_list_warns_centres_are_used():
    vox, pts, pb, l2i = scene()
    _, msgs = project(vox, pts[:0], pb[:0], l2i)
    assert any("centre" in m and "empty" in m for m in msgs), msgs


def test_checks_can_be_switched_off():
    vox, pts, pb, l2i = scene()
    assert any("empty" in m for m in project(vox, pts[:0], pb[:0], l2i)[1])  # on by default on the CPU
    set_geometry_checks(False)
    try:
        _, msgs = project(vox, pts[:0], pb[:0], l2i)
    finally:
        set_geometry_checks(None)
    assert msgs == []


def _inputs(levels, size=HW):
    _, pts, pb, l2i = scene()
    return FusionInputs(levels, l2i, size, pts, pb)


def test_levels_finest_first_and_each_the_image_over_a_stride():
    fine, coarse = torch.zeros(1, 4, 120, 160), torch.zeros(1, 4, 60, 80)
    _inputs([fine, coarse])
    _inputs([fine, torch.zeros(1, 4, 15, 20), torch.zeros(1, 4, 8, 10)])  # /32 rounds up: within a pixel
    with pytest.raises(MSSFError, match=r"finest first.*reversed"):
        _inputs([coarse, fine])
    with pytest.raises(MSSFError, match=r"image_features\[1\].*over a stride"):
        _inputs([fine, torch.zeros(1, 4, 60, 60)])


def test_channels_last_level_is_named():
    with pytest.raises(MSSFError, match=r"image_features\[0\].*channels-last.*permute\(0, 3, 1, 2\)"):
        _inputs([torch.zeros(1, 120, 160, 4)])
    with pytest.raises(MSSFError, match=r"image_features\[1\].*channels-last"):
        _inputs([torch.zeros(1, 4, 120, 160), torch.zeros(1, 60, 80, 4)])


def test_apply_image_augmentation_takes_the_4x4_lidar2img_the_projector_takes():
    from mssf_blocks.geometry import apply_image_augmentation, image_augmentation_matrix

    vox, pts, pb, l2i = scene()
    l2i44 = torch.cat([l2i, torch.tensor([[[0.0, 0, 0, 1]]])], 1)  # (1, 4, 4)
    a, size = image_augmentation_matrix(HW, resize=(240, 320), flip=True)
    out44 = apply_image_augmentation(l2i44, a)
    assert out44.shape == (1, 4, 4) and torch.equal(out44[:, 3], l2i44[:, 3])
    # the same rows as the 3 x 4 matrix's (computed by hand here: A @ P in float64)
    torch.testing.assert_close(out44[:, :3].double(), (a @ l2i[0].double())[None], rtol=0, atol=1e-4)
    p34, _ = project(vox, pts, pb, apply_image_augmentation(l2i, a), size)
    p44, _ = project(vox, pts, pb, out44, size)
    assert torch.equal(p34.uv, p44.uv) and torch.equal(p34.valid, p44.valid)
