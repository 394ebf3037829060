"""mssf_examples.data.augment: global flip / rotation / scaling / translation with the projection kept exact.

References are independent of the code under test: box membership by ``points_in_boxes`` before and
after, pixels recomputed from the un-augmented points with the scene's own ``lidar2img`` and read with
``F.grid_sample``, rotations written out with cos / sin, azimuths from ``atan2``.
"""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks import MSSFError, VoxelCentroidProjector, points_in_boxes
from mssf_blocks.functional import voxelize_points
from mssf_blocks.samplers import sample_at_projection
from mssf_examples.data.augment import (
    NO_AUGMENTATION,
    AugmentationConfig,
    SampleAugmentation,
    augment_batch,
    augment_batches,
    augment_boxes,
    augment_points,
    draw_augmentation,
)
from mssf_examples.data.batch import RadarCameraBatch
from mssf_examples.models.presets import TJ4D_RECIPE, VOD_RECIPE
from mssf_examples.scenes.synthetic import Scene, SceneConfig, generate_scene

KINDS = VOD_RECIPE.feature_kinds  # the scenes' 7 columns are VoD's
CFG = SceneConfig(image_size=(64, 100))


@pytest.fixture(scope="module")
def scenes():
    return [generate_scene(s, CFG) for s in (11, 12, 13)]


def fixed(flip=False, rotation=0.0, scale=1.0, translation=(0.0, 0.0, 0.0), image_flip=None):
    return SampleAugmentation(flip, rotation, scale, translation, flip if image_flip is None else image_flip)


CASES = {
    "flip": fixed(flip=True),
    "flip_no_image": fixed(flip=True, image_flip=False),
    "rotation": fixed(rotation=0.7),
    "scale": fixed(scale=1.05),
    "translation": fixed(translation=(0.8, -1.3, 0.2)),
    "all": fixed(flip=True, rotation=-0.6, scale=0.95, translation=(-0.5, 0.4, -0.1)),
}


def random_cases(n=4, seed=5):
    cfg = AugmentationConfig(translation_std=(0.5, 0.5, 0.1))
    g = torch.Generator().manual_seed(seed)
    return [draw_augmentation(cfg, g) for _ in range(n)]


def batch_of(scenes, features=None):
    b = Scene.collate(scenes)
    if features is not None:
        from dataclasses import replace

        b = replace(b, images=None, image_features=features, image_size=scenes[0].image_size)
    return b


def apply_fixed(batch, aug, monkeypatch):
    """augment_batch with every sample given the draw ``aug``."""
    import mssf_examples.data.augment as A

    monkeypatch.setattr(A, "draw_augmentation", lambda cfg, g: aug)
    cfg = AugmentationConfig(sync_image_flip=aug.image_flip or not aug.flip)
    out, draws = augment_batch(batch, KINDS, cfg, torch.Generator())
    assert draws == [aug] * batch.batch_size
    return out


def clear_membership(points, boxes, tol=1e-4):
    """``(P, G)`` membership and a mask of the points farther than ``tol`` from every box face."""
    loose = points_in_boxes(points, boxes, margin=tol)
    shrunk = boxes.clone()
    shrunk[:, 3:6] = (shrunk[:, 3:6] - 2 * tol).clamp(min=0)
    tight = points_in_boxes(points, shrunk)
    return tight, (loose == tight).all(1)


@pytest.mark.parametrize("name", [*CASES, "random0", "random1", "random2", "random3"])
def test_boxes_keep_exactly_their_points(scenes, name, monkeypatch):
    aug = CASES[name] if name in CASES else random_cases()[int(name[-1])]
    batch = batch_of(scenes)
    out = apply_fixed(batch, aug, monkeypatch)
    inside_total = 0
    for p0, g0, p1, g1 in zip(batch.points, batch.gt_boxes, out.points, out.gt_boxes):
        before, clear = clear_membership(p0[:, :3].double(), g0.double())
        after = points_in_boxes(p1[:, :3].double(), g1.double(), eps=1e-3)
        after_strict = points_in_boxes(p1[:, :3].double(), g1.double(), eps=0.0)
        # every point well inside stays inside, every point well outside stays outside
        assert torch.equal(after[clear] & before[clear], before[clear])
        assert not (after_strict[clear] & ~before[clear]).any()
        inside_total += int(before[clear].sum())
        assert torch.equal(out.gt_labels[0], batch.gt_labels[0])
    assert inside_total > 30  # the scenes have objects with points


def _pixels_reference(points0, scene_l2i, image, size):
    """Bilinear read of ``image (C, H, W)`` at the projection of ``points0 (N, 3)`` (float64, by hand)."""
    h, w = size
    hom = torch.cat([points0, torch.ones(len(points0), 1, dtype=torch.float64)], 1) @ scene_l2i.double().T
    d = hom[:, 2]
    u, v = hom[:, 0] / d, hom[:, 1] / d
    grid = torch.stack([2 * (u + 0.5) / w - 1, 2 * (v + 0.5) / h - 1], 1)[None, None]
    ref = F.grid_sample(image[None].double(), grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    ref = ref[0, :, 0].T
    inside = (d > 1e-5) & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    return torch.where(inside[:, None], ref, torch.zeros_like(ref)), inside


RANGE = (-40.0, -40.0, -8.0, 40.0, 40.0, 8.0)
VOXEL = (0.4, 0.4, 0.5)


def check_same_pixels(batch, out, image_ref, image_aug, rng=RANGE, voxel=VOXEL, atol=2e-4):
    """Every voxel centroid of the augmented batch ``out`` samples from ``image_aug (B, V, C, H, W)`` what
    its member points, taken back to the un-augmented frame (same rows), give in ``image_ref``.

    Returns the number of (voxel, camera) hits inside the image."""
    pts, pb = out.flat_points()
    vox = voxelize_points(pts, pb, out.batch_size, voxel, rng[:3], rng[3:])
    proj = VoxelCentroidProjector()(vox, pts[:, :3], pb, out.lidar2img, out.image_size, out.points_to_sensor)
    got = sample_at_projection(image_aug, proj)
    assert proj.has_points.all()
    p0_all, _ = batch.flat_points()
    # member points by the voxelizer's rule floor((p - lo) / voxel), in the points' dtype as it computes it
    idx = torch.stack([torch.floor((pts[:, k] - rng[k]) / voxel[k]).long() for k in range(3)], 1)
    d, hh, ww = vox.spatial_shape
    in_grid = (idx >= 0).all(1) & (idx[:, 0] < ww) & (idx[:, 1] < hh) & (idx[:, 2] < d)
    keys = torch.where(in_grid, ((pb * d + idx[:, 2]) * hh + idx[:, 1]) * ww + idx[:, 0], -1)
    c = vox.coords.long()
    vkeys = ((c[:, 0] * d + c[:, 1]) * hh + c[:, 2]) * ww + c[:, 3]
    checked = 0
    h, w = batch.image_size
    for b in range(batch.batch_size):
        rows = (c[:, 0] == b).nonzero().flatten()
        cent0 = torch.stack([p0_all[keys == vkeys[r], :3].double().mean(0) for r in rows])
        ref, inside = _pixels_reference(cent0, batch.lidar2img[b, 0], image_ref[b, 0], (h, w))
        torch.testing.assert_close(got[rows].double(), ref, rtol=0, atol=atol)
        checked += int(inside.sum())
    return checked


@pytest.mark.parametrize("use_features", [False, True])
@pytest.mark.parametrize("name", [*CASES, "random0", "random1", "random2", "random3"])
def test_voxel_centroids_see_the_same_pixels(scenes, name, use_features, monkeypatch):
    aug = CASES[name] if name in CASES else random_cases()[int(name[-1])]
    torch.manual_seed(0)
    h, w = CFG.image_size
    # a smooth random feature map (so a pixel shift changes the value), or the rendered images
    feats = F.interpolate(torch.rand(len(scenes), 1, 3, 16, 25).flatten(0, 1), size=(h, w), mode="bilinear",
                          align_corners=False).unflatten(0, (len(scenes), 1))
    batch = batch_of(scenes, [feats] if use_features else None)
    if not use_features:
        feats = batch.images
    out = apply_fixed(batch, aug, monkeypatch)
    image_aug = out.image_features[0] if use_features else out.images
    assert check_same_pixels(batch, out, feats, image_aug) > 50


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["all", "flip", "random0", "random1"])
def test_real_vod_frames(realdata_root, name, monkeypatch):
    """The two real VoD frames (single radar scan, 1936 x 1216 image, the real calibration)."""
    from mssf_examples.data.kitti_io import VOD_RADAR, KittiFormatDataset, frames_to_batch

    root = realdata_root / "vod"
    if not root.is_dir():
        pytest.skip(f"VoD frames not found at {root}")
    ds = KittiFormatDataset(root, VOD_RADAR, sensor="radar")
    batch = frames_to_batch([ds.load(f) for f in ds.frame_ids])
    aug = CASES[name] if name in CASES else random_cases()[int(name[-1])]
    out = apply_fixed(batch, aug, monkeypatch)
    assert check_same_pixels(batch, out, batch.images, out.images, rng=(-80.0, -80.0, -10.0, 80.0, 80.0, 10.0),
                             atol=1e-4) > 100
    for p0, g0, p1, g1 in zip(batch.points, batch.gt_boxes, out.points, out.gt_boxes):
        before, clear = clear_membership(p0[:, :3].double(), g0.double())
        after = points_in_boxes(p1[:, :3].double(), g1.double(), eps=1e-3)
        assert torch.equal(after[clear], before[clear]) and before[clear].any()
    assert all(torch.equal(p0[:, 3:], p1[:, 3:]) for p0, p1 in zip(batch.points, out.points))


def test_missing_inverse_or_corner_flip_is_detected(scenes, monkeypatch):
    # The reference above must be able to fail: drop points_to_sensor after a rotation.
    out = apply_fixed(batch_of(scenes), CASES["all"], monkeypatch)
    pts, pb = out.flat_points()
    vox = voxelize_points(pts, pb, out.batch_size, VOXEL, RANGE[:3], RANGE[3:])
    right = sample_at_projection(out.images, VoxelCentroidProjector()(vox, pts[:, :3], pb, out.lidar2img, out.image_size,
                                                                      out.points_to_sensor))
    wrong = sample_at_projection(out.images, VoxelCentroidProjector()(vox, pts[:, :3], pb, out.lidar2img, out.image_size))
    assert (right - wrong).abs().max() > 0.05


def test_feature_columns_change_only_where_they_should():
    g = torch.Generator().manual_seed(0)
    p = torch.randn(200, 7, generator=g, dtype=torch.float64) * 5
    p[:, 0] = p[:, 0].abs() + 1
    aug = fixed(flip=True, rotation=0.4, scale=1.03, translation=(0.3, -0.2, 0.1))
    out = augment_points(p, aug, KINDS)
    assert torch.equal(out[:, 3:], p[:, 3:])  # RCS, v_r, v_rc, t: the same bits
    x, y, z = p[:, 0], -p[:, 1], p[:, 2]  # flip y -> -y first
    c, s = math.cos(0.4), math.sin(0.4)
    ref = torch.stack([1.03 * (c * x - s * y) + 0.3, 1.03 * (s * x + c * y) - 0.2, 1.03 * z + 0.1], 1)
    torch.testing.assert_close(out[:, :3], ref, rtol=0, atol=1e-12)
    # azimuth / elevation columns (TJ4DRadSet's Alpha / Beta once declared): without translation the
    # augmented azimuth is atan2 of the augmented point, the elevation keeps its value
    q = torch.cat([p[:, :3], torch.atan2(p[:, 1], p[:, 0])[:, None], torch.rad2deg(torch.atan2(p[:, 1], p[:, 0]))[:, None],
                   torch.atan2(p[:, 2], p[:, :2].norm(dim=1))[:, None]], 1)
    kinds = ("x", "y", "z", "azimuth_rad", "azimuth_deg", "elevation")
    for a in (fixed(flip=True, rotation=0.4, scale=1.03), fixed(rotation=-2.9), fixed(flip=True)):
        o = augment_points(q, a, kinds)
        az = torch.atan2(o[:, 1], o[:, 0])
        torch.testing.assert_close(o[:, 3], az, rtol=0, atol=1e-9)
        torch.testing.assert_close(o[:, 4], torch.rad2deg(az), rtol=0, atol=1e-7)
        torch.testing.assert_close(o[:, 5], torch.atan2(o[:, 2], o[:, :2].norm(dim=1)), rtol=0, atol=1e-9)


def test_box_yaw_and_size():
    box = torch.tensor([[10.0, 2.0, -1.0, 4.0, 1.8, 1.5, 0.3, 7.0]], dtype=torch.float64)
    out = augment_boxes(box, fixed(flip=True, rotation=0.5, scale=1.02))
    torch.testing.assert_close(out[0, 3:6], box[0, 3:6] * 1.02)
    assert out[0, 6].item() == pytest.approx(-0.3 + 0.5)
    assert out[0, 7].item() == 7.0
    # heading vector flipped then rotated
    hx, hy = math.cos(0.3), -math.sin(0.3)
    c, s = math.cos(0.5), math.sin(0.5)
    assert math.atan2(s * hx + c * hy, c * hx - s * hy) == pytest.approx(out[0, 6].item())


def test_deterministic_under_a_seed_and_draw_statistics(scenes):
    cfg = AugmentationConfig(translation_std=(0.2, 0.2, 0.0))

    def run(seed):
        return list(augment_batches([batch_of(scenes[:2]), batch_of(scenes[1:])], KINDS, cfg, seed))

    a, b, c = run(0), run(0), run(1)
    for x, y in zip(a, b):
        assert all(torch.equal(p, q) for p, q in zip(x.points, y.points))
        assert torch.equal(x.points_to_sensor, y.points_to_sensor) and torch.equal(x.images, y.images)
    assert not all(torch.equal(p, q) for p, q in zip(a[0].points, c[0].points))
    g = torch.Generator().manual_seed(3)
    draws = [draw_augmentation(AugmentationConfig(), g) for _ in range(400)]
    assert 0.4 < sum(d.flip for d in draws) / 400 < 0.6
    assert all(d.image_flip == d.flip for d in draws)
    assert all(-math.pi / 4 <= d.rotation <= math.pi / 4 and 0.95 <= d.scale <= 1.05 for d in draws)
    assert all(d.translation == (0.0, 0.0, 0.0) for d in draws)
    assert min(d.rotation for d in draws) < -0.7 and max(d.rotation for d in draws) > 0.7


def test_identity_config_changes_nothing(scenes):
    b = batch_of(scenes)
    out, _ = augment_batch(b, KINDS, NO_AUGMENTATION, torch.Generator().manual_seed(0))
    assert all(torch.equal(p, q) for p, q in zip(out.points, b.points))
    assert torch.equal(out.lidar2img, b.lidar2img) and torch.equal(out.images, b.images)
    torch.testing.assert_close(out.points_to_sensor, torch.eye(4).expand(3, 4, 4))
    assert NO_AUGMENTATION.is_identity and not AugmentationConfig().is_identity


def test_gt_range_filter_after_augmenting():
    b = RadarCameraBatch(points=[torch.zeros(1, 7)], lidar2img=torch.zeros(1, 1, 3, 4), image_size=(4, 4),
                         gt_boxes=[torch.tensor([[1.0, 0.0, 0, 1, 1, 1, 0], [5.0, 0.0, 0, 1, 1, 1, 0]])],
                         gt_labels=[torch.tensor([0, 1])])
    cfg = AugmentationConfig(flip_prob=0.0, rotation_range=(math.pi / 2, math.pi / 2), scale_range=(1.0, 1.0),
                             gt_range=(0.0, -3.0, -3.0, 10.0, 3.0, 3.0))
    out, _ = augment_batch(b, KINDS, cfg, torch.Generator())
    # rotated by 90 deg: (1, 0) -> (0, 1) stays; (5, 0) -> (0, 5) leaves |y| < 3
    assert out.gt_labels[0].tolist() == [0]


def test_recipes_name_the_dataset_columns():
    from mssf_examples.data.kitti_io import TJ4D_RADAR, VOD_RADAR

    assert VOD_RECIPE.feature_names == VOD_RADAR.features
    assert TJ4D_RECIPE.feature_names == TJ4D_RADAR.features
    assert VOD_RECIPE.peak_lr(2) == pytest.approx(5e-3) and VOD_RECIPE.peak_lr(1) == pytest.approx(1e-2)
    assert TJ4D_RECIPE.peak_lr(2) == pytest.approx(1e-2)


def test_bad_inputs():
    with pytest.raises(MSSFError, match="flip_prob"):
        AugmentationConfig(flip_prob=1.5)
    with pytest.raises(MSSFError, match="scale_range"):
        AugmentationConfig(scale_range=(0.0, 1.0))
    with pytest.raises(MSSFError, match="rotation_range"):
        AugmentationConfig(rotation_range=(1.0, -1.0))
    with pytest.raises(MSSFError, match="translation_std"):
        AugmentationConfig(translation_std=(0.0, -1.0, 0.0))
    with pytest.raises(MSSFError, match="feature_kinds: expected one kind per point column"):
        augment_points(torch.zeros(2, 5), fixed(), KINDS)
    with pytest.raises(MSSFError, match="feature_kinds: expected kinds from"):
        augment_points(torch.zeros(2, 4), fixed(), ("x", "y", "z", "velocity"))
    with pytest.raises(MSSFError, match="boxes: expected shape"):
        augment_boxes(torch.zeros(2, 6), fixed())
