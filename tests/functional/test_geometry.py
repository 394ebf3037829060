"""voxel_centers, voxel_centroids and project_points against independent references."""

import math

import pytest
import torch

from mssf_blocks import MSSFError
from mssf_blocks.functional.geometry import (
    project_points,
    voxel_centers,
    voxel_centroids,
    voxel_centroids_reference,
)

VOXEL = (0.2, 0.25, 0.5)
LO = (0.0, -2.0, -1.0)
HI = (4.0, 2.0, 1.0)
BASE_SHAPE = (4, 16, 20)  # (D, H, W) = ((1 - -1)/0.5, 4/0.25, 4/0.2)


def naive_centroids(points, batch, coords, stride, voxel=VOXEL, lo=LO, hi=HI):
    """Independent reference: for each voxel, scan every point (O(N * P)) in float64 Python."""
    sz, sy, sx = stride
    out, has = [], []
    pts = points.double().tolist()
    bs = batch.tolist()
    for b, z, y, x in coords.tolist():
        acc, cnt = [0.0, 0.0, 0.0], 0
        for (px, py, pz, *_), pb in zip(pts, bs):
            if pb != b or not (lo[0] <= px < hi[0] and lo[1] <= py < hi[1] and lo[2] <= pz < hi[2]):
                continue
            ix = math.floor((px - lo[0]) / voxel[0]) // sx
            iy = math.floor((py - lo[1]) / voxel[1]) // sy
            iz = math.floor((pz - lo[2]) / voxel[2]) // sz
            if (ix, iy, iz) == (x, y, z):
                acc = [acc[0] + px, acc[1] + py, acc[2] + pz]
                cnt += 1
        if cnt:
            out.append([a / cnt for a in acc])
        else:  # the centre
            out.append([(x + 0.5) * voxel[0] * sx + lo[0], (y + 0.5) * voxel[1] * sy + lo[1], (z + 0.5) * voxel[2] * sz + lo[2]])
        has.append(cnt > 0)
    return torch.tensor(out, dtype=torch.float64), torch.tensor(has)


def random_scene(seed, counts=(120, 0, 37), stride=(1, 1, 1), dilate=6, outside=10):
    """Points per batch element (one element without points), voxels at ``stride`` holding them plus
    ``dilate`` extra empty voxels per sample (as sparse-conv dilation creates) and points outside the range."""
    g = torch.Generator().manual_seed(seed)
    pts, bat = [], []
    for b, n in enumerate(counts):
        lo, hi = torch.tensor(LO, dtype=torch.float64), torch.tensor(HI, dtype=torch.float64)
        p = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
        # Clusters so that voxels hold several points.
        p[: n // 2] = p[: n // 4 + 1].repeat(3, 1)[: n // 2] + 0.01 * torch.randn(n // 2, 3, generator=g, dtype=torch.float64)
        p = torch.minimum(torch.maximum(p, lo), hi - 1e-6)
        pts.append(p)
        bat.append(torch.full((n,), b, dtype=torch.long))
    # Points outside the range (must be ignored).
    out = torch.tensor(HI, dtype=torch.float64) + torch.rand(outside, 3, generator=g, dtype=torch.float64)
    out[::2] = torch.tensor(LO, dtype=torch.float64) - torch.rand(len(out[::2]), 3, generator=g, dtype=torch.float64) - 1e-3
    pts.append(out)
    bat.append(torch.zeros(outside, dtype=torch.long))
    points = torch.cat(pts)
    extra = torch.randn(points.shape[0], 2, generator=g, dtype=torch.float64)  # RCS, Doppler: ignored
    points = torch.cat([points, extra], dim=1)
    batch = torch.cat(bat)
    sz, sy, sx = stride
    shape = tuple(-(-s // k) for s, k in zip(BASE_SHAPE, stride))
    inside = ((points[:, :3] >= torch.tensor(LO, dtype=torch.float64)) & (points[:, :3] < torch.tensor(HI, dtype=torch.float64))).all(1)
    idx = torch.floor((points[inside, :3] - torch.tensor(LO, dtype=torch.float64)) / torch.tensor(VOXEL, dtype=torch.float64)).long()
    zyx = torch.stack([idx[:, 2] // sz, idx[:, 1] // sy, idx[:, 0] // sx], 1)
    coords = torch.unique(torch.cat([batch[inside, None], zyx], 1), dim=0)
    empties = []
    for b in range(len(counts)):
        e = torch.stack([torch.randint(0, s, (dilate,), generator=g) for s in shape], 1)
        empties.append(torch.cat([torch.full((dilate, 1), b), e], 1))
    coords = torch.unique(torch.cat([coords] + empties), dim=0)
    perm = torch.randperm(coords.shape[0], generator=g)  # never assume rows grouped by batch
    return points, batch, coords[perm].int(), shape


@pytest.mark.parametrize("stride", [(1, 1, 1), (2, 2, 2), (4, 4, 4), (1, 2, 2)])
@pytest.mark.parametrize("seed", [0, 1])
def test_centroids_equal_naive_loop(stride, seed):
    points, batch, coords, shape = random_scene(seed, stride=stride)
    got, has = voxel_centroids(points, batch, coords, shape, 3, VOXEL, LO, stride, point_range_max=HI)
    ref, ref_has = naive_centroids(points, batch, coords, stride)
    assert torch.equal(has, ref_has)
    assert has.any() and (~has).any()  # both kinds present
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
    # Batch element 1 has no points: every voxel of it uses the centre.
    assert not has[coords[:, 0] == 1].any()
    # The library's own slow reference agrees as well.
    lib_ref, lib_has = voxel_centroids_reference(points, batch, coords, shape, 3, VOXEL, LO, stride, HI)
    torch.testing.assert_close(lib_ref, ref)
    assert torch.equal(lib_has, ref_has)


def test_centroids_float32_close_to_float64():
    points, batch, coords, shape = random_scene(3, stride=(2, 2, 2))
    got32, has32 = voxel_centroids(points.float(), batch, coords, shape, 3, VOXEL, LO, (2, 2, 2), HI)
    ref, ref_has = naive_centroids(points, batch, coords, (2, 2, 2))
    assert got32.dtype == torch.float32 and torch.equal(has32, ref_has)
    torch.testing.assert_close(got32.double(), ref, rtol=1e-5, atol=1e-5)


def test_centroids_without_range_max_ignores_points_beyond_grid():
    points, batch, coords, shape = random_scene(4)
    got, _ = voxel_centroids(points, batch, coords, shape, 3, VOXEL, LO)
    ref, _ = naive_centroids(points, batch, coords, (1, 1, 1))  # grid end == HI here
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)


def test_centroids_permutation_equivariant():
    points, batch, coords, shape = random_scene(5, stride=(1, 2, 2))
    base, has = voxel_centroids(points, batch, coords, shape, 3, VOXEL, LO, (1, 2, 2), HI)
    g = torch.Generator().manual_seed(0)
    pp = torch.randperm(points.shape[0], generator=g)
    vp = torch.randperm(coords.shape[0], generator=g)
    got, got_has = voxel_centroids(points[pp], batch[pp], coords[vp], shape, 3, VOXEL, LO, (1, 2, 2), HI)
    torch.testing.assert_close(got, base[vp], rtol=1e-12, atol=1e-12)
    assert torch.equal(got_has, has[vp])


def test_centroids_duplicate_rows_share_value_and_empty_inputs():
    points = torch.tensor([[0.05, -1.9, -0.9], [0.15, -1.95, -0.8]], dtype=torch.float64)
    batch = torch.zeros(2, dtype=torch.long)
    coords = torch.tensor([[0, 0, 0, 0], [0, 0, 0, 0]], dtype=torch.int32)
    got, has = voxel_centroids(points, batch, coords, BASE_SHAPE, 1, VOXEL, LO)
    torch.testing.assert_close(got, torch.tensor([[0.1, -1.925, -0.85]] * 2, dtype=torch.float64))
    assert has.all()
    # No voxels.
    c0, h0 = voxel_centroids(points, batch, torch.zeros(0, 4, dtype=torch.int32), BASE_SHAPE, 1, VOXEL, LO)
    assert c0.shape == (0, 3) and h0.shape == (0,)
    # No points: every voxel gets its centre.
    c1, h1 = voxel_centroids(points[:0], batch[:0], coords, BASE_SHAPE, 1, VOXEL, LO)
    torch.testing.assert_close(c1, voxel_centers(coords, VOXEL, LO, dtype=torch.float64))
    assert not h1.any()


@pytest.mark.parametrize(
    "change, pattern",
    [
        (dict(points=torch.zeros(3, 2)), r"points: expected shape \(P, >=3\)"),
        (dict(points=torch.tensor([[float("nan"), 0, 0]] * 3)), r"points\[:, :3\]: expected finite"),
        (dict(points_batch=torch.zeros(2, dtype=torch.long)), r"points_batch: expected shape \(3,\)"),
        (dict(points_batch=torch.zeros(3)), r"points_batch: expected dtype"),
        (dict(points_batch=torch.tensor([0, 0, 5])), r"points_batch: expected values in \[0, 2\)"),
        (dict(coords=torch.zeros(2, 3, dtype=torch.int32)), r"coords: expected shape"),
        (dict(coords=torch.zeros(2, 4)), r"coords: expected dtype"),
        (dict(point_range_max=(0.0, 0.0, 0.0)), r"point_range_max: expected every value above"),
    ],
)
def test_centroid_bad_input(change, pattern):
    args = dict(
        points=torch.zeros(3, 3), points_batch=torch.zeros(3, dtype=torch.long),
        coords=torch.zeros(2, 4, dtype=torch.int32), spatial_shape=BASE_SHAPE, batch_size=2,
        voxel_size=VOXEL, point_range_min=LO,
    )
    args.update(change)
    with pytest.raises(MSSFError, match=pattern):
        voxel_centroids(**args)


# ---------------------------------------------------------------------------------------------------
# Projection

# Sensor frame: x forward, y left, z up. Camera: x right = -y, y down = -z, z forward = x.
R_S2C = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 200.0, 40.0], [0.0, 0.0, 1.0]], dtype=torch.float64)


def pinhole(t=(0.0, 0.0, 0.0)):
    rt = torch.cat([R_S2C, torch.tensor(t, dtype=torch.float64)[:, None]], 1)
    return K @ rt  # (3, 4)


def test_projection_hand_worked():
    # Sensor point (4, -1, -2) -> camera (1, 2, 4): u = 100 * 1/4 + 50 = 75, v = 200 * 2/4 + 40 = 140,
    # depth 4. Image 200 x 160 (H x W): uv = (75.5 / 160, 140.5 / 200) = (0.471875, 0.7025).
    pts = torch.tensor([[4.0, -1.0, -2.0]], dtype=torch.float64)
    out = project_points(pts, torch.zeros(1, dtype=torch.long), pinhole()[None], (200, 160))
    torch.testing.assert_close(out.pixel[0, 0], torch.tensor([75.0, 140.0], dtype=torch.float64))
    torch.testing.assert_close(out.uv[0, 0], torch.tensor([0.471875, 0.7025], dtype=torch.float64))
    torch.testing.assert_close(out.depth[0, 0], torch.tensor(4.0, dtype=torch.float64))
    assert out.valid.tolist() == [[True]]


def test_projection_pixel_centre_lands_at_half_pixel():
    # A point on pixel centre (i, j) of a W x H image: uv = ((i + 0.5) / W, (j + 0.5) / H).
    W, H = 96, 64
    i = torch.arange(0, W, 7, dtype=torch.float64)
    j = torch.arange(0, H, 5, dtype=torch.float64)[: len(i)]
    i = i[: len(j)]
    d = 3.0 + torch.arange(len(i), dtype=torch.float64)
    cam = torch.stack([(i - 50.0) / 100.0 * d, (j - 40.0) / 200.0 * d, d], 1)
    sensor = cam @ R_S2C  # inverse of a rotation
    out = project_points(sensor, torch.zeros(len(i), dtype=torch.long), pinhole()[None], (H, W))
    torch.testing.assert_close(out.uv[:, 0, 0], (i + 0.5) / W, rtol=0, atol=1e-12)
    torch.testing.assert_close(out.uv[:, 0, 1], (j + 0.5) / H, rtol=0, atol=1e-12)
    assert out.valid.all()


def test_projection_behind_and_outside_invalid_without_nan():
    pts = torch.tensor(
        [[-4.0, 0.0, 0.0],  # behind
         [0.0, 0.0, 0.0],   # on the camera centre (depth 0)
         [4.0, -100.0, 0.0],  # far right: outside
         [4.0, 0.0, 0.0]],  # inside
        dtype=torch.float64, requires_grad=True)
    out = project_points(pts, torch.zeros(4, dtype=torch.long), pinhole()[None], (200, 160))
    assert out.valid[:, 0].tolist() == [False, False, False, True]
    assert torch.isfinite(out.uv).all() and torch.isfinite(out.pixel).all()
    assert (out.uv[:2] == -1).all()
    out.uv.sum().backward()
    assert torch.isfinite(pts.grad).all()
    assert (pts.grad[:2] == 0).all()  # invalid depth: no gradient


def test_projection_augmentation_inverse_restores():
    from mssf_blocks import augmentation_matrix

    g = torch.Generator().manual_seed(0)
    pts = torch.stack([torch.rand(50, generator=g, dtype=torch.float64) * 20 + 2,
                       torch.rand(50, generator=g, dtype=torch.float64) * 10 - 5,
                       torch.rand(50, generator=g, dtype=torch.float64) * 2 - 1], 1)
    batch = torch.arange(50) % 2
    l2i = torch.stack([pinhole(), pinhole((0.1, -0.2, 0.3))])
    plain = project_points(pts, batch, l2i, (200, 160))
    augs = torch.stack([
        augmentation_matrix(flip_x=True, rotation=0.3, scale=1.05, translation=(0.5, -0.2, 0.1)),
        augmentation_matrix(flip_y=True, rotation=-0.7, scale=0.95, translation=(-1.0, 0.3, 0.0)),
    ])
    hom = torch.cat([pts, torch.ones(50, 1, dtype=torch.float64)], 1)
    aug_pts = torch.einsum("nij,nj->ni", augs[batch], hom)[:, :3]
    assert not torch.allclose(aug_pts, pts)
    restored = project_points(aug_pts, batch, l2i, (200, 160), points_to_sensor=torch.linalg.inv(augs))
    torch.testing.assert_close(restored.uv, plain.uv, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(restored.depth, plain.depth, rtol=1e-10, atol=1e-10)
    assert torch.equal(restored.valid, plain.valid)


def test_projection_two_cameras_per_camera_results():
    pts = torch.tensor([[5.0, 1.0, 0.5], [6.0, -2.0, 0.0], [-3.0, 0.0, 0.0]], dtype=torch.float64)
    batch = torch.tensor([0, 1, 1])
    cam_a = pinhole()
    # Camera b looks backwards (sensor -x): rotate the sensor frame by pi about z first.
    rz = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64))
    cam_b = pinhole() @ rz
    l2i = torch.stack([torch.stack([cam_a, cam_b])] * 2)  # (B=2, V=2, 3, 4)
    out = project_points(pts, batch, l2i, (200, 160))
    assert out.uv.shape == (3, 2, 2) and out.valid.shape == (3, 2)
    for v, m in enumerate([cam_a, cam_b]):
        single = project_points(pts, batch, m[None].expand(2, 3, 4), (200, 160))
        torch.testing.assert_close(out.uv[:, v], single.uv[:, 0])
        assert torch.equal(out.valid[:, v], single.valid[:, 0])
    # The point behind the front camera is in front of the rear one.
    assert out.valid[2].tolist() == [False, True]


@pytest.mark.parametrize(
    "change, pattern",
    [
        (dict(lidar2img=torch.full((1, 3, 4), float("nan"))), r"lidar2img: expected finite"),
        (dict(lidar2img=torch.zeros(1, 2, 4)), r"lidar2img: expected shape \(B, V, 3, 4\)"),
        (dict(points_batch=torch.tensor([0, 1])), r"points_batch: expected values in \[0, 1\)"),
        (dict(points_to_sensor=torch.zeros(1, 4, 4)), r"points_to_sensor: expected affine"),
        (dict(points_to_sensor=torch.tensor([[[1.0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]])), r"points_to_sensor: expected invertible"),
        (dict(points_to_sensor=torch.eye(4).expand(2, 4, 4)), r"points_to_sensor: expected shape \(1, 4, 4\)"),
        (dict(image_size=(0, 10)), r"image_size: expected positive"),
        (dict(points=torch.zeros(2, 2)), r"points: expected shape \(N, >=3\)"),
    ],
)
def test_projection_bad_input(change, pattern):
    args = dict(points=torch.zeros(2, 3), points_batch=torch.zeros(2, dtype=torch.long),
                lidar2img=pinhole().float()[None], image_size=(10, 10))
    args.update(change)
    with pytest.raises(MSSFError, match=pattern):
        project_points(**args)
