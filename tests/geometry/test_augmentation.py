"""image_augmentation_matrix / apply_image_augmentation: image flips, resizes and crops folded into lidar2img.

The claim under test: sampling the augmented image at the augmented projection returns what the original
image gives at the original projection. The augmented images are built independently of the matrices
(``torch.flip``, slicing, ``F.interpolate(align_corners=False)`` read at its own pixel centres), in float64.
"""

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks import (
    MSSFError,
    SparseVoxels,
    VoxelCentroidProjector,
    apply_image_augmentation,
    augmentation_matrix,
    image_augmentation_matrix,
)
from mssf_blocks.samplers import sample_at_projection
from mssf_blocks.testing import TOLERANCES

_RTOL, _ATOL = TOLERANCES[torch.float64]
TOL = dict(rtol=_RTOL, atol=_ATOL)
H, W = 12, 16


def l2i_front():
    # Sensor x forward = depth; u = 8 - 10 y / x, v = 6 - 10 z / x (f = 10 px, principal point (8, 6)).
    return torch.tensor([[[8.0, -10.0, 0.0, 0.0], [6.0, 0.0, -10.0, 0.0], [1.0, 0.0, 0.0, 0.0]]], dtype=torch.float64)


def points_at_pixels(uv, depth):
    """Sensor points that :func:`l2i_front` projects to pixel ``uv (P, 2)`` at ``depth (P,)``."""
    x = depth
    return torch.stack([x, (8.0 - uv[:, 0]) * x / 10.0, (6.0 - uv[:, 1]) * x / 10.0], 1)


def sample(image, points, lidar2img, image_size, points_to_sensor=None):
    """``(P, C)``: the fusion blocks' bilinear sample of ``image`` at every point (one point per voxel)."""
    vs = 0.05
    # A grid one voxel wider than the points, indices computed as the centroid code does (floor((p - lo) / vs)).
    lo = torch.floor(points.min(0).values / vs) * vs - vs
    idx = torch.floor((points - lo) / vs).long()[:, [2, 1, 0]]  # (z, y, x)
    shape = tuple(int(s) + 2 for s in idx.max(0).values)
    coords = torch.cat([torch.zeros(len(points), 1, dtype=torch.long), idx], 1).int()
    assert len(torch.unique(coords, dim=0)) == len(points)  # test set-up: one point per voxel
    origin = tuple(float(v) for v in lo)
    vox = SparseVoxels(torch.zeros(len(points), 1, dtype=torch.float64), coords, shape, 1, voxel_size=(vs, vs, vs), point_range_min=origin)
    proj = VoxelCentroidProjector()(vox, points, torch.zeros(len(points), dtype=torch.long), lidar2img, image_size,
                                    points_to_sensor)
    return sample_at_projection(image, proj)


@pytest.fixture
def image():
    torch.manual_seed(0)
    return torch.randn(1, 3, H, W, dtype=torch.float64)


def random_inside(n, h, w, margin=1.0, seed=1):
    g = torch.Generator().manual_seed(seed)
    u = margin + torch.rand(n, generator=g, dtype=torch.float64) * (w - 1 - 2 * margin)
    v = margin + torch.rand(n, generator=g, dtype=torch.float64) * (h - 1 - 2 * margin)
    return torch.stack([u, v], 1)


def test_hand_worked_matrices():
    a, size = image_augmentation_matrix((4, 6), flip=True)
    assert size == (4, 6)
    torch.testing.assert_close(a, torch.tensor([[-1.0, 0, 5], [0, 1, 0], [0, 0, 1]], dtype=torch.float64))
    # Resize 4 x 6 -> 8 x 12: pixel 0's left edge (-0.5) stays at -0.5, its centre 0 goes to 0.5.
    a, size = image_augmentation_matrix((4, 6), resize=(8, 12))
    assert size == (8, 12)
    torch.testing.assert_close(a @ torch.tensor([-0.5, 0.0, 1.0], dtype=torch.float64),
                               torch.tensor([-0.5, 0.5, 1.0], dtype=torch.float64))
    a, size = image_augmentation_matrix((4, 6), crop=(1, 2, 3, 3))
    assert size == (3, 3)
    torch.testing.assert_close(a @ torch.tensor([2.0, 1.0, 1.0], dtype=torch.float64),
                               torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))


def test_flip_exact(image):
    uv = random_inside(40, H, W)
    pts = points_at_pixels(uv, torch.linspace(2.0, 9.0, 40, dtype=torch.float64))
    a, size = image_augmentation_matrix((H, W), flip=True)
    ref = sample(image, pts, l2i_front(), (H, W))
    got = sample(torch.flip(image, [-1]), pts, apply_image_augmentation(l2i_front(), a), size)
    torch.testing.assert_close(got, ref, **TOL)
    assert ref.abs().sum() > 1  # the points see the image
    # The corner-origin flip u -> W - u is half a pixel off in this convention and must not pass.
    wrong = torch.tensor([[-1.0, 0, W], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
    bad = sample(torch.flip(image, [-1]), pts, apply_image_augmentation(l2i_front(), wrong), size)
    assert (bad - ref).abs().max() > 1e-2


def test_crop_exact(image):
    uv = random_inside(40, H, W, margin=3.0)
    pts = points_at_pixels(uv, torch.linspace(2.0, 9.0, 40, dtype=torch.float64))
    top, left, ch, cw = 2, 3, 8, 11
    a, size = image_augmentation_matrix((H, W), crop=(top, left, ch, cw))
    assert size == (ch, cw)
    cropped = image[..., top:top + ch, left:left + cw]
    inside = (uv[:, 0] - left > 0) & (uv[:, 0] - left < cw - 1) & (uv[:, 1] - top > 0) & (uv[:, 1] - top < ch - 1)
    assert inside.sum() > 10
    ref = sample(image, pts, l2i_front(), (H, W))[inside]
    got = sample(cropped, pts, apply_image_augmentation(l2i_front(), a), size)[inside]
    torch.testing.assert_close(got, ref, **TOL)


@pytest.mark.parametrize("new_size", [(18, 24), (6, 8), (24, 20)])
def test_resize_exact_at_pixel_centres(image, new_size):
    a, size = image_augmentation_matrix((H, W), resize=new_size)
    assert size == new_size
    resized = F.interpolate(image, size=new_size, mode="bilinear", align_corners=False)
    # Points whose augmented projection is a pixel centre of the resized image: there the resized image
    # holds exactly the original image's bilinear value at the original projection.
    jj, ii = torch.meshgrid(torch.arange(1, new_size[1] - 1), torch.arange(1, new_size[0] - 1), indexing="xy")
    uv_new = torch.stack([jj.flatten(), ii.flatten()], 1).double()
    uv = (torch.linalg.inv(a) @ torch.cat([uv_new, torch.ones(len(uv_new), 1, dtype=torch.float64)], 1).T).T[:, :2]
    pts = points_at_pixels(uv, 3.0 + 0.01 * torch.arange(len(uv), dtype=torch.float64))
    l2i_aug = apply_image_augmentation(l2i_front(), a)
    got = sample(resized, pts, l2i_aug, size)
    torch.testing.assert_close(got, resized[0, :, ii.flatten(), jj.flatten()].T, **TOL)  # exact pixel hits
    torch.testing.assert_close(got, sample(image, pts, l2i_front(), (H, W)), **TOL)
    # The projector must be given the augmented size: the original one samples elsewhere.
    assert (sample(resized, pts, l2i_aug, (H, W)) - got).abs().max() > 1e-2


def test_products_resize_crop_flip(image):
    # resize 12 x 16 -> 18 x 24, crop 12 x 16 at (2, 3), flip; reference image by index operations.
    a, size = image_augmentation_matrix((H, W), resize=(18, 24), crop=(2, 3, 12, 16), flip=True)
    final = torch.flip(F.interpolate(image, size=(18, 24), mode="bilinear", align_corners=False)[..., 2:14, 3:19], [-1])
    assert size == tuple(final.shape[-2:])
    # The same product from single-step matrices.
    r, s1 = image_augmentation_matrix((H, W), resize=(18, 24))
    c, s2 = image_augmentation_matrix(s1, crop=(2, 3, 12, 16))
    f, s3 = image_augmentation_matrix(s2, flip=True)
    torch.testing.assert_close(f @ c @ r, a, **TOL)
    assert s3 == size
    jj, ii = torch.meshgrid(torch.arange(1, size[1] - 1), torch.arange(1, size[0] - 1), indexing="xy")
    uv_new = torch.stack([jj.flatten(), ii.flatten()], 1).double()
    uv = (torch.linalg.inv(a) @ torch.cat([uv_new, torch.ones(len(uv_new), 1, dtype=torch.float64)], 1).T).T[:, :2]
    pts = points_at_pixels(uv, 3.0 + 0.01 * torch.arange(len(uv), dtype=torch.float64))
    got = sample(final, pts, apply_image_augmentation(l2i_front(), a), size)
    torch.testing.assert_close(got, final[0, :, ii.flatten(), jj.flatten()].T, **TOL)
    torch.testing.assert_close(got, sample(image, pts, l2i_front(), (H, W)), **TOL)


def test_product_flip_then_downscale(image):
    # Other order: flip first, then resize to half size; A = R @ Fl.
    fl, s1 = image_augmentation_matrix((H, W), flip=True)
    r, s2 = image_augmentation_matrix(s1, resize=(6, 8))
    a = r @ fl
    final = F.interpolate(torch.flip(image, [-1]), size=s2, mode="bilinear", align_corners=False)
    jj, ii = torch.meshgrid(torch.arange(0, 8), torch.arange(0, 6), indexing="xy")
    uv_new = torch.stack([jj.flatten(), ii.flatten()], 1).double()
    uv = (torch.linalg.inv(a) @ torch.cat([uv_new, torch.ones(len(uv_new), 1, dtype=torch.float64)], 1).T).T[:, :2]
    pts = points_at_pixels(uv, 3.0 + 0.01 * torch.arange(len(uv), dtype=torch.float64))
    got = sample(final, pts, apply_image_augmentation(l2i_front(), a), s2)
    torch.testing.assert_close(got, sample(image, pts, l2i_front(), (H, W)), **TOL)


def test_with_point_augmentation_sync_flip(image):
    # The authors' synchronised flip: points y -> -y and the image mirrored; with points_to_sensor and
    # lidar2img' = A @ lidar2img every augmented point samples the original image's feature.
    uv = random_inside(40, H, W)
    pts = points_at_pixels(uv, torch.linspace(2.0, 9.0, 40, dtype=torch.float64))
    m = augmentation_matrix(flip_x=True, rotation=0.3, scale=1.04, translation=(0.2, -0.1, 0.05))
    pts_aug = (m[:3, :3] @ pts.T).T + m[:3, 3]
    a, size = image_augmentation_matrix((H, W), flip=True)
    got = sample(torch.flip(image, [-1]), pts_aug, apply_image_augmentation(l2i_front(), a), size,
                 torch.linalg.inv(m)[None])
    torch.testing.assert_close(got, sample(image, pts, l2i_front(), (H, W)), **TOL)


def test_apply_shapes_and_dtype():
    a, _ = image_augmentation_matrix((H, W), flip=True)
    l2i = l2i_front().float().expand(2, 3, 3, 4).clone()  # (B, V, 3, 4)
    out = apply_image_augmentation(l2i, a)
    assert out.shape == (2, 3, 3, 4) and out.dtype == torch.float32
    torch.testing.assert_close(out[1, 2], (a @ l2i_front()[0]).float())
    per_sample = torch.stack([a, torch.eye(3, dtype=torch.float64)])  # (B, 3, 3)
    out = apply_image_augmentation(l2i, per_sample)
    torch.testing.assert_close(out[1], l2i[1])
    torch.testing.assert_close(apply_image_augmentation(l2i_front(), a[None]), (a @ l2i_front()[0])[None])


def test_errors():
    with pytest.raises(MSSFError, match="image_size: expected"):
        image_augmentation_matrix((0, 4))
    with pytest.raises(MSSFError, match="resize: expected"):
        image_augmentation_matrix((4, 4), resize=(2.5, 3))
    with pytest.raises(MSSFError, match="crop: expected"):
        image_augmentation_matrix((4, 4), crop=(0, 0, 2))
    with pytest.raises(MSSFError, match="lidar2img: expected shape"):
        apply_image_augmentation(torch.zeros(3, 4), torch.eye(3))
    with pytest.raises(MSSFError, match="matrix: expected one of"):
        apply_image_augmentation(torch.zeros(2, 1, 3, 4), torch.eye(3).expand(3, 3, 3))
    with pytest.raises(MSSFError, match="last row"):
        apply_image_augmentation(torch.zeros(1, 3, 4), torch.ones(3, 3))
