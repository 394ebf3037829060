"""MSSF backbones with OpenPCDet's backbones_3d contract, built from a YAML model config.

The config is read as OpenPCDet's ``cfg_from_yaml_file`` reads it (``yaml.safe_load`` into an
``EasyDict``); the backbone is built as ``Detector3DTemplate.build_backbone_3d`` builds it (keyword
arguments ``model_cfg``, ``input_channels``, ``grid_size``, ``voxel_size``, ``point_cloud_range``, the
grid computed like ``DataProcessor``); the batch carries what ``MeanVFE`` and the KITTI dataset put
into it. Sizes are shrunk (coarser voxels, narrow image levels) to run on a CPU.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")
yaml = pytest.importorskip("yaml")
easydict = pytest.importorskip("easydict")

from mssf_blocks import MSSFError  # noqa: E402
from mssf_blocks.integrations.openpcdet import augmentor_order  # noqa: E402
from mssf_blocks.integrations.openpcdet_backbones import OPENPCDET_BACKBONES, settings_from_model_cfg  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")  # spconv's CPU kernels, tiny tensors
CONFIGS = Path(__file__).resolve().parents[2] / "examples" / "configs" / "openpcdet"
CONFIG = CONFIGS / "vod_models" / "mssf_second.yaml"


def read_config(path=CONFIG):
    """The model config with its DATA_CONFIG._BASE_CONFIG_ merged in (as cfg_from_yaml_file from tools/)."""
    cfg = yaml.safe_load(path.read_text())
    base = cfg["DATA_CONFIG"].pop("_BASE_CONFIG_")
    cfg["DATA_CONFIG"] = {**yaml.safe_load((CONFIGS / "dataset_configs" / Path(base).name).read_text()), **cfg["DATA_CONFIG"]}
    return easydict.EasyDict(cfg)


def load_cfg(**backbone):
    cfg = read_config()
    cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE = [0.8, 0.8, 0.125]  # 64 x 64 x 40 cells on the CPU
    cfg.MODEL.BACKBONE_3D.update(IMAGE_CHANNELS=[8, 8], MSDFF_HEADS=2, MSDFF_POINTS=2, SEG_HIDDEN=[16], **backbone)
    return cfg


def build_backbone(cfg, input_channels=7):
    pcr = np.array(cfg.DATA_CONFIG.POINT_CLOUD_RANGE, dtype=np.float32)
    voxel_size = cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE
    grid_size = np.round((pcr[3:6] - pcr[0:3]) / np.array(voxel_size)).astype(np.int64)  # DataProcessor
    all_backbones = dict(OPENPCDET_BACKBONES)  # pcdet/models/backbones_3d/__init__.py after the two lines
    return all_backbones[cfg.MODEL.BACKBONE_3D.NAME](
        model_cfg=cfg.MODEL.BACKBONE_3D, input_channels=input_channels, grid_size=grid_size,
        voxel_size=voxel_size, point_cloud_range=pcr,
    ), grid_size


def make_batch(cfg, batch_size=2, n=300, seed=0):
    gen = np.random.default_rng(seed)
    pcr = np.array(cfg.DATA_CONFIG.POINT_CLOUD_RANGE)
    vs = np.array(cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE)
    pts, coords, feats = [], [], []
    for b in range(batch_size):
        xyz = gen.uniform(pcr[:3] + [4, 0, 0], pcr[3:] - 1e-3, (n, 3))
        p = np.concatenate([xyz, gen.normal(size=(n, 4))], 1).astype(np.float32)
        idx = np.floor((xyz - pcr[:3]) / vs).astype(np.int64)
        keys, inv = np.unique(idx[:, ::-1], axis=0, return_inverse=True)  # (z, y, x)
        mean = np.zeros((len(keys), 7))
        np.add.at(mean, inv.reshape(-1), p)
        mean /= np.bincount(inv.reshape(-1))[:, None]  # MeanVFE
        pts.append(np.pad(p, ((0, 0), (1, 0)), constant_values=b))
        coords.append(np.pad(keys, ((0, 0), (1, 0)), constant_values=b))
        feats.append(mean)
    h, w = 96, 320
    k = np.array([[300.0, 0, w / 2, 0], [0, 300, h / 2, 0], [0, 0, 1, 0]])
    l2c = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0.3], [1, 0, 0, 0], [0, 0, 0, 1]])  # camera looks along +x
    batch = {
        "points": torch.from_numpy(np.concatenate(pts)).float(),
        "voxel_coords": torch.from_numpy(np.concatenate(coords)).float(),  # load_data_to_gpu: float
        "voxel_features": torch.from_numpy(np.concatenate(feats)).float(),
        "batch_size": batch_size,
        "images": torch.zeros(batch_size, 3, h, w),
        "trans_lidar_to_cam": torch.from_numpy(np.stack([l2c] * batch_size)).float(),
        "trans_cam_to_img": torch.from_numpy(np.stack([k] * batch_size)).float(),
        "image_shape": torch.tensor([[h, w]] * batch_size, dtype=torch.int32),
        "flip_x": torch.tensor([1.0, 0.0]), "noise_rot": torch.tensor([0.1, -0.2]), "noise_scale": torch.tensor([1.0, 1.02]),
        "gt_boxes": torch.tensor([[[20.0, 0, -0.5, 8, 8, 3, 0.3, 1], [0, 0, 0, 0, 0, 0, 0, 0]],
                                  [[30.0, 5, -0.5, 6, 6, 3, -0.4, 2], [15, -5, -1, 10, 10, 4, 0, 1]]]),
    }
    batch["image_fpn"] = tuple(torch.randn(batch_size, 8, h // s, w // s, requires_grad=True) for s in (8, 16))
    return batch


def test_config_builds_the_openpcdet_contract():
    cfg = load_cfg()
    assert augmentor_order(cfg.DATA_CONFIG.DATA_AUGMENTOR) == tuple(cfg.MODEL.BACKBONE_3D.AUG_ORDER)
    net, grid_size = build_backbone(cfg)
    # OpenPCDet's VoxelBackBone8x: sparse_shape = grid_size[::-1] + [1, 0, 0], 128 output features
    assert net.sparse_shape == (grid_size[::-1] + [1, 0, 0]).tolist()
    assert net.num_point_features == 128
    assert net.backbone_channels == {"x_conv1": 16, "x_conv2": 32, "x_conv3": 64, "x_conv4": 64}
    assert net.num_fusion_blocks == 2
    assert net.net.stages[0].fusion.value_proj.out_features == 8  # the paper's width: the image channels
    narrow, _ = build_backbone(load_cfg(MSDFF_VALUE_DIM="voxel_channels"))
    assert narrow.net.stages[0].fusion.value_proj.out_features == 16
    res, _ = build_backbone(load_cfg(NAME="MSSFVoxelResBackBone8x", NUM_FUSION_BLOCKS=0))
    assert res.backbone_channels == {"x_conv1": 16, "x_conv2": 32, "x_conv3": 64, "x_conv4": 128}


@pytest.mark.parametrize("name", ["MSSFVoxelBackBone8x", "MSSFVoxelResBackBone8x"])
def test_forward_backward_on_an_openpcdet_batch(name):
    torch.manual_seed(0)
    cfg = load_cfg(NAME=name)
    net, grid_size = build_backbone(cfg)
    batch = make_batch(cfg)
    out = net(batch)
    assert out is batch
    enc = out["encoded_spconv_tensor"]
    assert out["encoded_spconv_tensor_stride"] == 8
    assert out["multi_scale_3d_strides"] == {"x_conv1": 1, "x_conv2": 2, "x_conv3": 4, "x_conv4": 8}
    assert sorted(out["multi_scale_3d_features"]) == ["x_conv1", "x_conv2", "x_conv3", "x_conv4"]
    assert list(out["multi_scale_3d_features"]["x_conv2"].spatial_shape) == [21, 32, 32]
    # HeightCompression: dense (B, C, D, H, W) -> (B, C * D, H, W) = NUM_BEV_FEATURES
    bev = enc.dense()
    n, c, d, h, w = bev.shape
    assert (n, c * d, h, w) == (2, cfg.MODEL.MAP_TO_BEV.NUM_BEV_FEATURES, 8, 8)
    loss_seg, tb = net.get_loss(batch)
    assert loss_seg.item() > 0 and "loss_mssf_seg" in tb
    (bev.square().mean() + loss_seg).backward()
    img_grads = [lvl.grad for lvl in batch["image_fpn"]]
    assert all(g is not None and g.abs().sum() > 0 for g in img_grads)
    fusion_params = [p for n_, p in net.named_parameters() if "fusion" in n_]
    assert fusion_params and all(p.grad is not None for p in fusion_params)


def test_radar_only_needs_no_camera_keys():
    cfg = load_cfg(NUM_FUSION_BLOCKS=0)
    net, _ = build_backbone(cfg)
    batch = make_batch(cfg)
    for key in ("images", "trans_lidar_to_cam", "trans_cam_to_img", "image_fpn"):
        del batch[key]
    out = net(batch)
    assert "mssf_seg_logits" not in out and out["encoded_spconv_tensor"].features.shape[1] == 128


def test_config_errors_name_the_key():
    with pytest.raises(MSSFError, match="NUM_FUSION_BLCOKS"):
        settings_from_model_cfg({"NAME": "MSSFVoxelBackBone8x", "NUM_FUSION_BLCOKS": 2})
    cfg = load_cfg()
    pcr = np.array(cfg.DATA_CONFIG.POINT_CLOUD_RANGE)
    with pytest.raises(MSSFError, match="grid_size"):
        OPENPCDET_BACKBONES["MSSFVoxelBackBone8x"](cfg.MODEL.BACKBONE_3D, 7, np.array([10, 10, 10]),
                                                   voxel_size=[0.8, 0.8, 0.125], point_cloud_range=pcr)
