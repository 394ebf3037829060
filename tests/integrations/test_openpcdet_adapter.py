"""OpenPCDet batch_dict -> FusionInputs, on batches built the way OpenPCDet builds them.

The helpers below re-state OpenPCDet's documented data path (no OpenPCDet import): KITTI's
``__getitem__`` camera keys (``calib_to_matricies``: ``trans_lidar_to_cam = R0 @ V2C``,
``trans_cam_to_img = P2``), ``augmentor_utils`` (``random_flip_along_x``: ``y -> -y``;
``global_rotation``: ``rotate_points_along_z``, row vectors times ``[[c, s, 0], [-s, c, 0], [0, 0, 1]]``;
``global_scaling``; ``random_world_translation``: ``(1, 3)`` noise added), ``collate_batch`` (batch
column padded onto the points, images padded bottom/right, other keys ``np.stack``) and
``load_data_to_gpu`` (images to ``(B, 3, H, W)``, ``image_shape`` to int, the rest to float).
The reference projection is a float64 numpy ``P2 @ R0 @ V2C`` of the *original* points.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mssf_blocks import MSSFError
from mssf_blocks.functional.geometry import project_points
from mssf_blocks.integrations.openpcdet import (
    augmentor_order,
    camera_from_batch_dict,
    fusion_inputs_from_batch_dict,
    lidar_aug_matrices,
)

RNG = np.random.default_rng(0)


# ------------------------------------------------------------------ OpenPCDet's data path, re-stated
def kitti_calib(shift: float):
    v2c = np.array([[0.0, -1, 0, 0.02], [0, 0, -1, 0.3 + shift], [1, 0, 0, -0.1]], dtype=np.float32)
    r0 = np.eye(3, dtype=np.float32)
    r0[:2, :2] = [[math.cos(0.01), -math.sin(0.01)], [math.sin(0.01), math.cos(0.01)]]
    p2 = np.array([[700.0, 0, 300 + 10 * shift, 40.0], [0, 710, 120, 0.2], [0, 0, 1, 0.003]], dtype=np.float32)
    l2c = np.vstack([v2c, [0, 0, 0, 1]]).astype(np.float32)
    r04 = np.eye(4, dtype=np.float32)
    r04[:3, :3] = r0
    return r04 @ l2c, p2  # calib_to_matricies: V2R = R0 @ V2C, P2


def kitti_sample(i: int, n: int = 200, hw=(120, 400)):
    pts = np.concatenate([RNG.uniform([4, -8, -2], [40, 8, 2], (n, 3)), RNG.uniform(0, 1, (n, 1))], 1).astype(np.float32)
    l2c, p2 = kitti_calib(0.1 * i)
    h, w = hw
    return {"points": pts, "images": RNG.uniform(0, 1, (h, w, 3)).astype(np.float32),
            "trans_lidar_to_cam": l2c, "trans_cam_to_img": p2, "image_shape": np.array([h, w], dtype=np.int32),
            "frame_id": f"{i:06d}"}


def flip_along_x(d):
    d["points"][:, 1] = -d["points"][:, 1]
    d["flip_x"] = np.True_


def flip_along_y(d):
    d["points"][:, 0] = -d["points"][:, 0]
    d["flip_y"] = np.True_


def rotation(d, angle):
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]], dtype=np.float32)
    d["points"][:, :3] = d["points"][:, :3] @ rot
    d["noise_rot"] = angle


def scaling(d, s):
    d["points"][:, :3] *= s
    d["noise_scale"] = s


def translation(d, t):
    noise = np.array([[t[0]], [t[1]], [t[2]]], dtype=np.float32).T  # (1, 3), as random_world_translation
    d["points"][:, :3] += noise
    d["noise_translate"] = noise


def collate_batch(samples):
    out = {}
    for key in samples[0]:
        vals = [s[key] for s in samples]
        if key == "points":
            out[key] = np.concatenate([np.pad(v, ((0, 0), (1, 0)), constant_values=i) for i, v in enumerate(vals)])
        elif key == "images":
            mh, mw = max(v.shape[0] for v in vals), max(v.shape[1] for v in vals)
            out[key] = np.stack([np.pad(v, ((0, mh - v.shape[0]), (0, mw - v.shape[1]), (0, 0))) for v in vals])
        elif key == "frame_id":
            out[key] = np.array(vals)
        else:
            out[key] = np.stack(vals, 0)
    out["batch_size"] = len(samples)
    return out


def load_data_to_gpu(batch):  # on the CPU here; same conversions
    for key, val in batch.items():
        if not isinstance(val, np.ndarray) or key == "frame_id":
            continue
        if key == "images":
            batch[key] = torch.from_numpy(val).permute(0, 3, 1, 2).float().contiguous()
        elif key == "image_shape":
            batch[key] = torch.from_numpy(val).int()
        else:
            batch[key] = torch.from_numpy(val).float()
    return batch


def reference_pixels(samples, batch_size):
    """float64 numpy ``(u, v, depth)`` of every original point under its own calibration."""
    out = []
    for s in samples:
        p = np.concatenate([s["points"][:, :3].astype(np.float64), np.ones((len(s["points"]), 1))], 1)
        cam = s["trans_cam_to_img"].astype(np.float64) @ s["trans_lidar_to_cam"].astype(np.float64) @ p.T
        out.append(np.stack([cam[0] / cam[2], cam[1] / cam[2], cam[2]], 1))
    return torch.from_numpy(np.concatenate(out))


def adapter_pixels(inputs):
    proj = project_points(inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size,
                          inputs.points_to_sensor)
    return proj.pixel[:, 0].double(), proj.depth[:, 0].double()


def fpn(batch_size, size, views=1, channels=8):
    h, w = size
    shape = (batch_size * views, channels) if views > 1 else (batch_size, channels)
    return tuple(torch.randn(*shape, h // s, w // s) for s in (4, 8))


def make_batches(augment, sizes=((120, 400), (110, 380))):
    import copy

    plain = [kitti_sample(i, hw=hw) for i, hw in enumerate(sizes)]
    aug = copy.deepcopy(plain)
    for i, d in enumerate(aug):
        augment(d, i)
    return plain, load_data_to_gpu(collate_batch(aug))


# ------------------------------------------------------------------ tests
def stock_augment(d, i):  # flip (x axis only, the KITTI/VoD setting) -> rotation -> scaling -> translation
    if i == 0:
        flip_along_x(d)
    else:
        d["flip_x"] = np.False_
    rotation(d, 0.3 - 0.5 * i)
    scaling(d, 1.04 - 0.07 * i)
    translation(d, (0.2, -0.1 * i, 0.05))


def test_augmented_kitti_batch_projects_like_the_original_points():
    plain, batch = make_batches(stock_augment)
    batch["image_fpn"] = fpn(2, batch["images"].shape[-2:])
    inputs = fusion_inputs_from_batch_dict(batch)
    ref = reference_pixels(plain, 2)
    pix, depth = adapter_pixels(inputs)
    torch.testing.assert_close(depth, ref[:, 2], rtol=0, atol=2e-4)
    torch.testing.assert_close(pix, ref[:, :2], rtol=0, atol=2e-3)  # float32 points, 700 px focal length
    assert inputs.image_size == (120, 400)  # the padded image tensor (padding is bottom/right)
    assert inputs.points.shape == (400, 3) and inputs.points_batch.tolist() == [0] * 200 + [1] * 200


def test_without_undoing_the_augmentation_the_projection_is_off():
    plain, batch = make_batches(stock_augment)
    batch["image_fpn"] = fpn(2, batch["images"].shape[-2:])
    inputs = fusion_inputs_from_batch_dict(batch)
    proj = project_points(inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size)
    assert (proj.depth[:, 0].double() - reference_pixels(plain, 2)[:, 2]).abs().max() > 0.5


def test_config_order_is_followed():
    def rot_then_flip(d, i):
        rotation(d, 0.4)
        flip_along_x(d)  # one flip: flipping both axes is a rotation by pi, which commutes

    plain, batch = make_batches(rot_then_flip)
    batch["image_fpn"] = fpn(2, batch["images"].shape[-2:])
    cfg = {"AUG_CONFIG_LIST": [{"NAME": "gt_sampling"}, {"NAME": "random_world_rotation"},
                               {"NAME": "random_world_flip"}, {"NAME": "random_world_scaling"}],
           "DISABLE_AUG_LIST": ["random_world_scaling"]}
    order = augmentor_order(cfg)
    assert order == ("random_world_rotation", "random_world_flip")
    ref = reference_pixels(plain, 2)
    pix, _ = adapter_pixels(fusion_inputs_from_batch_dict(batch, order=order))
    torch.testing.assert_close(pix, ref[:, :2], rtol=0, atol=2e-3)
    pix_default, _ = adapter_pixels(fusion_inputs_from_batch_dict(batch))  # flip -> rotation: wrong here
    assert (pix_default - ref[:, :2]).abs().max() > 10


def test_x_only_flip_is_undone_where_lidar_aug_matrix_misses_it():
    def flip_only(d, i):
        flip_along_x(d)
        # set_lidar_aug_matrix: the flips are read only when 'flip_y' is a key -> identity here
        d["lidar_aug_matrix"] = np.eye(4)

    plain, batch = make_batches(flip_only)
    m = lidar_aug_matrices(batch)
    torch.testing.assert_close(m[0], torch.diag(torch.tensor([1.0, -1, 1, 1], dtype=torch.float64)))
    batch["image_fpn"] = fpn(2, batch["images"].shape[-2:])
    pix, _ = adapter_pixels(fusion_inputs_from_batch_dict(batch))
    torch.testing.assert_close(pix, reference_pixels(plain, 2)[:, :2], rtol=0, atol=2e-3)


def test_lidar_aug_matrix_alone_is_used():
    def matrix_only(d, i):
        rotation(d, 0.25)
        del d["noise_rot"]
        c, s = math.cos(0.25), math.sin(0.25)
        d["lidar_aug_matrix"] = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])

    plain, batch = make_batches(matrix_only)
    batch["image_fpn"] = fpn(2, batch["images"].shape[-2:])
    pix, _ = adapter_pixels(fusion_inputs_from_batch_dict(batch))
    torch.testing.assert_close(pix, reference_pixels(plain, 2)[:, :2], rtol=0, atol=2e-3)


def test_evaluation_batch_has_no_points_to_sensor_and_numpy_batches_work():
    plain, batch = make_batches(lambda d, i: None)
    raw = collate_batch(plain)  # before load_data_to_gpu: numpy, images (B, H, W, 3)
    raw["points"] = torch.from_numpy(raw["points"])
    inputs = fusion_inputs_from_batch_dict(raw, image_features=fpn(2, (120, 400)))
    assert inputs.points_to_sensor is None and inputs.image_size == (120, 400)
    pix, _ = adapter_pixels(inputs)
    torch.testing.assert_close(pix, reference_pixels(plain, 2)[:, :2], rtol=0, atol=2e-3)


def image_calibrate(resize, crop, flip, rotate_deg):
    """OpenPCDet's DataProcessor.image_calibrate, re-stated: the (4, 4) post-homography of one view."""
    rot, trans = np.eye(2) * resize, -np.array(crop[:2], dtype=np.float64)
    if flip:
        a, b = np.array([[-1.0, 0], [0, 1]]), np.array([crop[2] - crop[0], 0.0])
        rot, trans = a @ rot, a @ trans + b
    th = rotate_deg / 180 * np.pi
    a = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
    b = np.array([crop[2] - crop[0], crop[3] - crop[1]]) / 2
    rot, trans = a @ rot, a @ trans + (a @ -b + b)
    m = np.eye(4)
    m[:2, :2], m[:2, 3] = rot, trans
    return m


def test_bevfusion_style_multiview_batch():
    b, v, h, w = 2, 3, 64, 176
    pts = [np.concatenate([RNG.uniform([-20, -20, -2], [20, 20, 2], (150, 3)), np.zeros((150, 2))], 1) for _ in range(b)]
    l2i = np.zeros((b, v, 4, 4))
    aug = np.zeros((b, v, 4, 4))
    ref_uv = []
    for i in range(b):
        for j in range(v):
            yaw = 2 * np.pi * j / v + 0.1 * i
            c, s = np.cos(yaw), np.sin(yaw)
            lidar2cam = np.eye(4)
            lidar2cam[:3, :3] = np.array([[-s, c, 0], [0, 0, -1], [c, s, 0]])  # optical axis along yaw
            k = np.eye(4)
            k[:3, :3] = [[120.0, 0, 400], [0, 120, 225], [0, 0, 1]]
            l2i[i, j] = k @ lidar2cam
            aug[i, j] = image_calibrate(0.22 + 0.01 * j, (12, 30, 12 + w, 30 + h), j == 1, 3.0 * (j - 1))
    m = np.stack([np.array([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) * [[1.05], [1.05], [1.05], [1]]
                  for _ in range(b)])
    m[:, :3, 3] = [0.3, -0.2, 0.1]
    for i in range(b):
        p = np.concatenate([pts[i][:, :3], np.ones((150, 1))], 1)
        for j in range(v):
            cam = l2i[i, j] @ p.T
            uv1 = np.stack([cam[0] / cam[2], cam[1] / cam[2], np.ones(150)])
            ref_uv.append((aug[i, j][[0, 1, 3]][:, [0, 1, 3]] @ uv1)[:2].T)  # 2-D post-homography on (u, v)
    aug_pts = [np.concatenate([(m[i] @ np.concatenate([pts[i][:, :3], np.ones((150, 1))], 1).T).T[:, :3], pts[i][:, 3:]], 1)
               for i in range(b)]
    batch = {
        "points": torch.from_numpy(np.concatenate([np.pad(p, ((0, 0), (1, 0)), constant_values=i) for i, p in enumerate(aug_pts)])).float(),
        "batch_size": b, "camera_imgs": torch.zeros(b, v, 3, h, w), "lidar2image": torch.from_numpy(l2i).float(),
        "img_aug_matrix": torch.from_numpy(aug).float(), "lidar_aug_matrix": torch.from_numpy(m).float(),
        "image_fpn": fpn(b, (h, w), views=v),
    }
    inputs = fusion_inputs_from_batch_dict(batch)
    assert inputs.num_cameras == v and inputs.image_features[0].shape == (b, v, 8, h // 4, w // 4)
    # (B*V) levels unfold sample-major: level[b, v] is row b * V + v of the folded tensor
    torch.testing.assert_close(inputs.image_features[1][1, 2], batch["image_fpn"][1][1 * v + 2])
    proj = project_points(inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size, inputs.points_to_sensor)
    got = proj.pixel.double().reshape(b, 150, v, 2).permute(0, 2, 1, 3).reshape(-1, 2)
    front = proj.depth.reshape(b, 150, v).permute(0, 2, 1).reshape(-1) > 0.5
    torch.testing.assert_close(got[front], torch.from_numpy(np.concatenate(ref_uv))[front], rtol=0, atol=5e-3)


def test_bad_inputs_raise_clear_errors():
    plain, batch = make_batches(stock_augment)
    with pytest.raises(MSSFError, match="image_fpn"):
        fusion_inputs_from_batch_dict(batch)
    with pytest.raises(MSSFError, match="B\\*V"):
        fusion_inputs_from_batch_dict(batch, image_features=[torch.zeros(3, 8, 30, 100)])
    with pytest.raises(MSSFError, match="order"):
        fusion_inputs_from_batch_dict(batch, image_features=fpn(2, (120, 400)), order=("random_world_flip",))
    bad = dict(batch, points=batch["points"][:, 1:3])
    with pytest.raises(MSSFError, match="batch index first"):
        fusion_inputs_from_batch_dict(bad, image_features=fpn(2, (120, 400)))
    no_cam = {k: v for k, v in batch.items() if k not in ("trans_lidar_to_cam", "trans_cam_to_img")}
    with pytest.raises(MSSFError, match="calib_matricies"):
        camera_from_batch_dict(no_cam)
    with pytest.raises(MSSFError, match="random_image_flip"):
        augmentor_order({"AUG_CONFIG_LIST": [{"NAME": "random_image_flip"}]})


def test_kitti_batch_with_a_resize_record_projects_into_the_resized_image():
    """``img_aug_matrix`` on a KITTI batch (the examples' image branch ``IMAGE_SIZE``): the pixels of the resized
    image, by hand: with edges aligned, pixel centre ``u`` of a ``W``-wide image lands at ``(u + 0.5) w / W - 0.5``
    of the ``w``-wide one (``v`` alike)."""
    plain, batch = make_batches(stock_augment)
    (h0, w0), (h, w) = batch["images"].shape[-2:], (30, 160)
    sx, sy = w / w0, h / h0
    m = np.eye(4)
    m[0, 0], m[1, 1], m[0, 3], m[1, 3] = sx, sy, 0.5 * sx - 0.5, 0.5 * sy - 0.5
    batch["img_aug_matrix"] = torch.from_numpy(np.broadcast_to(m, (2, 1, 4, 4)).copy()).float()
    batch["images"] = torch.nn.functional.interpolate(batch["images"], size=(h, w), mode="bilinear")
    batch["image_fpn"] = fpn(2, (h, w))
    inputs = fusion_inputs_from_batch_dict(batch)
    ref = reference_pixels(plain, 2)
    pix, depth = adapter_pixels(inputs)
    expected = torch.stack([(ref[:, 0] + 0.5) * sx - 0.5, (ref[:, 1] + 0.5) * sy - 0.5], 1)
    torch.testing.assert_close(depth, ref[:, 2], rtol=0, atol=2e-4)
    torch.testing.assert_close(pix, expected, rtol=0, atol=2e-3 * max(sx, sy) + 1e-6)
    assert inputs.image_size == (h, w)
    batch["img_aug_matrix"] = batch["img_aug_matrix"][:1]  # one record for a batch of two
    with pytest.raises(MSSFError, match="img_aug_matrix"):
        fusion_inputs_from_batch_dict(batch)
