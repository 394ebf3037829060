"""mmdet3d batch_inputs_dict + data_samples -> FusionInputs, on batches built the way mmdet3d builds them.

The helpers re-state mmdet3d 1.4's documented data path (no mmdet3d import): ``RandomFlip3D``
(``sync_2d``: the image is flipped with ``np.flip`` and ``flip`` / ``flip_direction`` /
``pcd_horizontal_flip`` recorded, points ``y -> -y``, flow ``'HF'``), ``GlobalRotScaleTrans``
(``rotation_3d_in_axis`` axis 2: ``p @ [[c, s, 0], [-s, c, 0], [0, 0, 1]]`` recorded as
``pcd_rotation``, then scale, then translation; flow ``'R', 'S', 'T'``), ``Pack3DDetInputs`` meta
keys, ``Det3DDataPreprocessor`` (images padded bottom/right to a multiple of 32,
``batch_input_shape`` / ``pad_shape`` set in the metainfo) and ``extract_img_feat`` (views folded
into the batch). References: float64 numpy projections of the original points.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from mssf_blocks import MSSFError
from mssf_blocks.functional.geometry import project_points
from mssf_blocks.functional.sampling import bilinear_sample
from mssf_blocks.geometry import image_augmentation_matrix
from mssf_blocks.integrations.mmdet3d import (
    fusion_inputs_from_data_samples,
    fusion_inputs_from_mmdet3d,
    image_aug_affine,
    lidar_aug_matrix,
)

RNG = np.random.default_rng(1)


try:  # Det3DDataSample's base class (mmdet3d.structures itself needs mmcv's compiled ops)
    from mmengine.structures import BaseDataElement as Sample
except ImportError:
    class Sample:  # the part of Det3DDataSample the adapter reads
        def __init__(self, metainfo):
            self.metainfo = dict(metainfo)

        def set_metainfo(self, metainfo):
            self.metainfo.update(metainfo)


def lidar2img(shift):
    lidar2cam = np.array([[0.0, -1, 0, 0.05], [0, 0, -1, 0.2 + shift], [1, 0, 0, 0.1], [0, 0, 0, 1]])
    cam2img = np.array([[500.0, 0, 200 + 20 * shift, 0], [0, 500, 90, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    return cam2img @ lidar2cam  # Det3DDataset: lidar2img = cam2img @ lidar2cam


def load(i, n=150, hw=(180, 400)):
    pts = np.concatenate([RNG.uniform([5, -6, -1.5], [30, 6, 1.5], (n, 3)), RNG.uniform(0, 1, (n, 2))], 1)
    return {"points": pts.astype(np.float32), "img": RNG.uniform(0, 1, hw + (3,)).astype(np.float32),
            "img_shape": hw, "ori_shape": hw, "lidar2img": lidar2img(0.1 * i)}


def random_flip_3d(r):  # RandomFlip3D(sync_2d=True), flip drawn True
    r["img"] = np.ascontiguousarray(r["img"][:, ::-1])
    r["flip"], r["flip_direction"] = True, "horizontal"
    r["pcd_horizontal_flip"], r["pcd_vertical_flip"] = True, False
    r["points"][:, 1] = -r["points"][:, 1]
    r.setdefault("transformation_3d_flow", []).append("HF")


def global_rot_scale_trans(r, angle, scale, trans):
    c, s = math.cos(angle), math.sin(angle)
    rot_mat_t = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]], dtype=np.float32)
    r["points"][:, :3] = r["points"][:, :3] @ rot_mat_t
    r["pcd_rotation"], r["pcd_rotation_angle"] = rot_mat_t, angle
    r["points"][:, :3] *= scale
    r["pcd_scale_factor"] = scale
    r["points"][:, :3] += np.asarray(trans, dtype=np.float32)
    r["pcd_trans"] = np.asarray(trans, dtype=np.float32)
    r.setdefault("transformation_3d_flow", []).extend(["R", "S", "T"])


META_KEYS = ("img_shape", "ori_shape", "lidar2img", "flip", "flip_direction", "pcd_horizontal_flip",
             "pcd_vertical_flip", "pcd_rotation", "pcd_rotation_angle", "pcd_scale_factor", "pcd_trans",
             "transformation_3d_flow", "scale_factor", "img_crop_offset", "lidar_aug_matrix", "img_aug_matrix")


def pack_and_preprocess(results, divisor=32):
    """Pack3DDetInputs + Det3DDataPreprocessor: points list, padded image batch, data samples."""
    imgs = [torch.from_numpy(r["img"]).permute(2, 0, 1) for r in results]
    mh = max(math.ceil(i.shape[1] / divisor) * divisor for i in imgs)
    mw = max(math.ceil(i.shape[2] / divisor) * divisor for i in imgs)
    batch = torch.stack([torch.nn.functional.pad(i, (0, mw - i.shape[2], 0, mh - i.shape[1])) for i in imgs])
    samples = []
    for r, i in zip(results, imgs):
        sample = Sample(metainfo={k: r[k] for k in META_KEYS if k in r})  # Pack3DDetInputs
        sample.set_metainfo({"batch_input_shape": (mh, mw),  # Det3DDataPreprocessor.simple_process
                             "pad_shape": (math.ceil(i.shape[1] / divisor) * divisor,
                                           math.ceil(i.shape[2] / divisor) * divisor)})
        samples.append(sample)
    return {"points": [torch.from_numpy(r["points"]) for r in results], "imgs": batch}, samples


def reference(results):
    out = []
    for r in results:
        p = np.concatenate([r["points"][:, :3].astype(np.float64), np.ones((len(r["points"]), 1))], 1)
        cam = r["lidar2img"] @ p.T
        out.append(np.stack([cam[0] / cam[2], cam[1] / cam[2], cam[2]], 1))
    return torch.from_numpy(np.concatenate(out))


def pixels(inputs, undo=True):
    proj = project_points(inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size,
                          inputs.points_to_sensor if undo else None)
    return proj


@pytest.mark.parametrize("flow", ["flip_first", "rotate_first"])  # KITTI configs / nuScenes configs
def test_augmented_batch_projects_like_the_original(flow):
    plain = [load(0), load(1, hw=(170, 390))]
    aug = copy.deepcopy(plain)
    for i, r in enumerate(aug):
        if flow == "flip_first":
            random_flip_3d(r)
            global_rot_scale_trans(r, 0.2 - 0.3 * i, 1.03, (0.2, -0.3, 0.05 * i))
        else:
            global_rot_scale_trans(r, 0.2 - 0.3 * i, 0.97, (0.1, 0.2, 0.0))
            random_flip_3d(r)
    inputs_dict, samples = pack_and_preprocess(aug)
    assert samples[0].metainfo["batch_input_shape"] == (192, 416)
    feats = [torch.randn(2, 4, 192 // s, 416 // s) for s in (4, 8)]
    inputs = fusion_inputs_from_data_samples(inputs_dict, samples, feats)
    assert inputs.image_size == (192, 416)
    ref = reference(plain)
    proj = pixels(inputs)
    torch.testing.assert_close(proj.depth[:, 0].double(), ref[:, 2], rtol=0, atol=1e-4)
    # the image is flipped: u -> W - 1 - u with W each sample's img_shape width
    w = torch.tensor([400.0] * 150 + [390.0] * 150, dtype=torch.float64)
    torch.testing.assert_close(proj.pixel[:, 0, 0].double(), w - 1 - ref[:, 0], rtol=0, atol=2e-3)
    torch.testing.assert_close(proj.pixel[:, 0, 1].double(), ref[:, 1], rtol=0, atol=2e-3)
    # ... and the flipped image holds the original content there (exact pixel-centre flip)
    img_orig = torch.stack([torch.nn.functional.pad(torch.from_numpy(r["img"]).permute(2, 0, 1), (0, 416 - r["img"].shape[1], 0, 192 - r["img"].shape[0])) for r in plain])
    uv_ref = torch.stack([(ref[:, 0] + 0.5) / 416, (ref[:, 1] + 0.5) / 192], 1)[:, None].float()
    valid = proj.valid & (uv_ref[..., 0] < w[:, None].float() / 416)
    got = bilinear_sample(inputs_dict["imgs"], proj.uv, inputs.points_batch, valid)
    want = bilinear_sample(img_orig, uv_ref, inputs.points_batch, valid)
    assert int(valid.sum()) > 100
    torch.testing.assert_close(got, want, rtol=0, atol=1e-3)
    # wrong order -> wrong projection (the flow matters)
    other = [dict(s.metainfo, transformation_3d_flow=list(reversed(s.metainfo["transformation_3d_flow"]))) for s in samples]
    bad = pixels(fusion_inputs_from_mmdet3d(inputs_dict["points"], feats, other))
    assert (bad.depth[:, 0].double() - ref[:, 2]).abs().max() > 0.3


def test_resize_crop_affine_is_exact_pixel_centre_form():
    meta = {"scale_factor": np.array([0.5, 0.5, 0.5, 0.5], dtype=np.float32), "img_crop_offset": [10, 4],
            "flip": True, "flip_direction": "horizontal", "img_shape": (90, 180)}
    a = image_aug_affine(meta, 1)[0]
    # hand-worked: u = 7 -> resize (7.5 * 0.5 - 0.5 = 3.25) -> crop (-6.75) -> flip (179 + 6.75);
    # v = 3 -> resize (3.5 * 0.5 - 0.5 = 1.25) -> crop (-2.75)
    torch.testing.assert_close(a @ torch.tensor([7.0, 3.0, 1.0], dtype=torch.float64),
                               torch.tensor([185.75, 1.25 - 4, 1.0], dtype=torch.float64))
    with pytest.raises(MSSFError, match="flip_direction"):
        image_aug_affine(dict(meta, flip_direction="vertical"), 1)
    # the library's image_augmentation_matrix: resize (200, 400) -> (100, 200), crop, flip
    lib, size = image_augmentation_matrix((200, 400), resize=(100, 200), crop=(4, 10, 90, 180), flip=True)
    torch.testing.assert_close(a, lib)
    with pytest.raises(MSSFError, match="per view"):
        image_aug_affine(meta, 3)
    torch.testing.assert_close(image_aug_affine({"scale_factor": 1.0}, 3), torch.eye(3, dtype=torch.float64).expand(3, 3, 3))


def test_multiview_bevfusion_meta_and_folded_features():
    b, v = 2, 4
    metas, pts, refs = [], [], []
    for i in range(b):
        l2i = np.stack([lidar2img(0.05 * j) @ np.diag([1.0, 1, 1, 1]) for j in range(v)])
        aug = np.tile(np.eye(4), (v, 1, 1))
        aug[:, 0, 0] = aug[:, 1, 1] = 0.48
        aug[:, :2, 3] = [-12.0, -20.0]
        m = np.eye(4)
        m[:3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]) * 1.02
        m[:3, 3] = [0.5, 0.0, -0.1]
        p = np.concatenate([RNG.uniform([5, -4, -1], [25, 4, 1], (80, 3)), np.zeros((80, 1))], 1)
        pts.append(torch.from_numpy(np.concatenate([(m @ np.c_[p[:, :3], np.ones(80)].T).T[:, :3], p[:, 3:]], 1)).float())
        metas.append({"lidar2img": l2i, "img_aug_matrix": aug, "lidar_aug_matrix": m, "batch_input_shape": (96, 192),
                      "transformation_3d_flow": ["R", "S", "T"]})  # lidar_aug_matrix wins over the pcd_* keys
        for j in range(v):
            cam = l2i[j] @ np.c_[p[:, :3], np.ones(80)].T
            refs.append(np.stack([0.48 * cam[0] / cam[2] - 12, 0.48 * cam[1] / cam[2] - 20], 1))
    feats = [torch.randn(b * v, 6, 96 // s, 192 // s) for s in (8, 16)]
    inputs = fusion_inputs_from_mmdet3d(pts, feats, metas)
    assert inputs.num_cameras == v and inputs.image_features[0].shape == (b, v, 6, 12, 24)
    torch.testing.assert_close(inputs.image_features[0][1, 3], feats[0][1 * v + 3])
    got = pixels(inputs).pixel.double().reshape(b, 80, v, 2).permute(0, 2, 1, 3).reshape(-1, 2)
    torch.testing.assert_close(got, torch.from_numpy(np.concatenate(refs)), rtol=0, atol=2e-3)


def test_metainfo_checks():
    eye = np.eye(3)
    assert torch.equal(lidar_aug_matrix({}), torch.eye(4, dtype=torch.float64))
    assert torch.equal(lidar_aug_matrix({"pcd_rotation": eye, "pcd_scale_factor": 1.0}), torch.eye(4, dtype=torch.float64))
    with pytest.raises(MSSFError, match="transformation_3d_flow"):
        lidar_aug_matrix({"pcd_horizontal_flip": True})
    with pytest.raises(MSSFError, match="listed twice"):
        lidar_aug_matrix({"transformation_3d_flow": ["R", "S", "T", "R", "S", "T"]})
    with pytest.raises(MSSFError, match="batch_input_metas"):
        fusion_inputs_from_mmdet3d([torch.zeros(3, 4)], [torch.zeros(1, 2, 4, 4)], [])
    with pytest.raises(MSSFError, match="list of"):
        fusion_inputs_from_mmdet3d(torch.zeros(3, 4), [torch.zeros(1, 2, 4, 4)], [{}])
