"""The mmdet3d plugin: registration with the real ``mmdet3d.registry.MODELS``, a config file, forward/backward.

The config is loaded with ``mmengine.Config.fromfile`` (which runs its ``custom_imports``, as
``tools/train.py`` does) and the middle encoder built with ``MODELS.build``. These tests also run with
mmcv-lite (no compiled ops: ``mmdet3d.registry`` imports, ``mmdet3d.models``, the registry's import
location pulled in on the first lookup, does not), so they mark that location as imported before
building; what is looked up and built is then exactly what the plugin registered, through mmengine's
own ``build_from_cfg``. Whole detectors trained in the real framework: ``test_mmdet3d_train.py``. The batch is built as mmdet3d builds it: ``Det3DDataPreprocessor``'s hard
voxelization (coors ``(batch, z, y, x)``), ``HardSimpleVFE`` means, metainfo with ``lidar2img`` and
the ``RandomFlip3D`` / ``GlobalRotScaleTrans`` keys, image levels ``(B*V, C, H, W)``.
"""

from __future__ import annotations

import importlib.util

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

from mssf_blocks import MSSFError  # noqa: E402
from mssf_blocks.integrations import mmdet3d_plugin  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
CONFIG = Path(__file__).resolve().parents[2] / "examples" / "configs" / "mmdet3d" / "mssf_second_vod.py"
SMALL = dict(voxel_size=[0.8, 0.8, 0.125], sparse_shape=[41, 64, 64], image_channels=[8, 8], msdff_heads=2,
             msdff_points=2, seg_hidden=[16])


def mmdet3d_models():
    registry = pytest.importorskip("mmdet3d.registry")
    return registry.MODELS


def build_from_config(models, **overrides):
    from mmengine.config import Config

    # custom_imports (mssf_examples.mmdet3d.plugin: the detector, dataset and metric) import mmdet3d.models,
    # which needs mmcv's compiled ops; with mmcv-lite (the compat environments) the encoder's registration
    # is the library plugin's, imported above
    cfg = Config.fromfile(str(CONFIG), import_custom_modules=importlib.util.find_spec("mmcv._ext") is not None)
    assert models.module_dict.get("MSSFSparseEncoder") is mmdet3d_plugin.MSSFSparseEncoder
    enc = cfg.model.pts_middle_encoder
    enc.update(SMALL, **overrides)
    models._imported = True  # see the module docstring: mmdet3d.models needs mmcv's compiled ops
    return models.build(enc), cfg


def make_batch(views=1, batch_size=2, n=300, seed=0):
    gen = np.random.default_rng(seed)
    pcr, vs = np.array([0, -25.6, -3, 51.2, 25.6, 2]), np.array(SMALL["voxel_size"])
    points, coors, feats, metas = [], [], [], []
    h, w = 96, 320
    for b in range(batch_size):
        xyz = gen.uniform(pcr[:3] + [4, 0, 0], pcr[3:] - 1e-3, (n, 3))
        p = np.concatenate([xyz, gen.normal(size=(n, 4))], 1)
        idx = np.floor((xyz - pcr[:3]) / vs).astype(np.int64)
        keys, inv = np.unique(idx[:, ::-1], axis=0, return_inverse=True)
        mean = np.zeros((len(keys), 7))
        np.add.at(mean, inv.reshape(-1), p)
        feats.append(mean / np.bincount(inv.reshape(-1))[:, None])  # HardSimpleVFE
        coors.append(np.pad(keys, ((0, 0), (1, 0)), constant_values=b))  # Det3DDataPreprocessor.voxelize
        points.append(torch.from_numpy(p).float())
        l2i = []
        for v in range(views):
            yaw = 0.3 * (v - (views - 1) / 2)
            c, s = math.cos(yaw), math.sin(yaw)
            lidar2cam = np.array([[-s, c, 0, 0], [0, 0, -1, 0.3], [c, s, 0, 0], [0, 0, 0, 1]])
            cam2img = np.array([[300.0, 0, w / 2, 0], [0, 300, h / 2, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            l2i.append(cam2img @ lidar2cam)
        c, s = math.cos(0.1 * b), math.sin(0.1 * b)
        metas.append({"lidar2img": np.stack(l2i) if views > 1 else l2i[0], "img_shape": (h, w), "pad_shape": (h, w),
                      "batch_input_shape": (h, w), "pcd_horizontal_flip": bool(b), "pcd_vertical_flip": False,
                      "pcd_rotation": np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]), "pcd_scale_factor": 1.01,
                      "pcd_trans": np.zeros(3), "transformation_3d_flow": ["HF", "R", "S", "T"] if b else ["R", "S", "T"]})
    coors = torch.from_numpy(np.concatenate(coors)).int()
    img_feats = [torch.randn(batch_size * views, 8, h // s, w // s, requires_grad=True) for s in (8, 16)]
    return torch.from_numpy(np.concatenate(feats)).float(), coors, points, img_feats, metas


@pytest.mark.parametrize("layout,views", [("VoxelBackBone8x", 1), ("VoxelResBackBone8x", 3)])
def test_build_from_config_and_train_one_step(layout, views):
    torch.manual_seed(0)
    encoder, cfg = build_from_config(mmdet3d_models(), layout=layout)
    assert isinstance(encoder, mmdet3d_plugin.MSSFSparseEncoder) and encoder.num_fusion_blocks == 2
    assert encoder.net.stages[0].fusion.value_proj.out_features == 8  # msdff_value_dim=None: image width
    voxel_features, coors, points, img_feats, metas = make_batch(views)
    batch_size = coors[-1, 0].item() + 1  # VoxelNet.extract_feat
    bev = encoder(voxel_features, coors, batch_size, points=points, img_features=img_feats, batch_input_metas=metas)
    assert bev.shape == (2, 256, 8, 8)  # SparseEncoder: (B, 128 * 2, H / 8, W / 8)
    gt = [torch.tensor([[20.0, 0, -2, 8, 8, 3, 0.3]]), torch.tensor([[30.0, 5, -2, 6, 6, 3, -0.4]])]
    loss_seg = encoder.seg_loss(points, gt)
    (bev.square().mean() + loss_seg).backward()
    assert all(f.grad is not None and f.grad.abs().sum() > 0 for f in img_feats)
    assert all(p.grad is not None for n, p in encoder.named_parameters() if "fusion" in n)
    mid_bev, stages = build_from_config(mmdet3d_models(), layout=layout, num_fusion_blocks=0,
                                        return_middle_feats=True)[0](voxel_features, coors, batch_size)
    assert mid_bev.shape == bev.shape and len(stages) == 4


def test_encoder_errors():
    encoder = mmdet3d_plugin.MSSFSparseEncoder(7, [41, 64, 64], [0, -25.6, -3, 51.2, 25.6, 2], [0.8, 0.8, 0.125],
                                               image_channels=[8, 8], msdff_heads=2, msdff_points=2)
    voxel_features, coors, points, img_feats, metas = make_batch()
    with pytest.raises(MSSFError, match="img_features, batch_input_metas: required"):
        encoder(voxel_features, coors, 2, points=points)
    with pytest.raises(MSSFError, match="sparse_shape"):
        mmdet3d_plugin.MSSFSparseEncoder(7, [40, 64, 64], [0, -25.6, -3, 51.2, 25.6, 2], [0.8, 0.8, 0.125],
                                        num_fusion_blocks=0)


def test_registration_with_an_mmengine_registry_and_without_mmdet3d(monkeypatch):
    mmengine_registry = pytest.importorskip("mmengine.registry")
    reg = mmengine_registry.Registry("mssf_test")
    assert mmdet3d_plugin.register_mmdet3d_modules(reg) and mmdet3d_plugin.register_mmdet3d_modules(reg)  # idempotent
    enc = reg.build(dict(type="MSSFSparseEncoder", in_channels=7, sparse_shape=[41, 64, 64],
                         point_cloud_range=[0, -25.6, -3, 51.2, 25.6, 2], voxel_size=[0.8, 0.8, 0.125],
                         num_fusion_blocks=0))
    assert isinstance(enc, mmdet3d_plugin.MSSFSparseEncoder)
    other = mmengine_registry.Registry("mssf_taken")
    other.register_module(name="MSSFSparseEncoder", module=torch.nn.Identity)
    with pytest.raises(MSSFError, match="already registered"):
        mmdet3d_plugin.register_mmdet3d_modules(other)
    # without mmdet3d (its import fails) the import-time registration registers nothing, quietly
    monkeypatch.setitem(sys.modules, "mmdet3d.registry", None)
    monkeypatch.setitem(sys.modules, "mmdet3d", None)
    assert mmdet3d_plugin.register_mmdet3d_modules() is False
