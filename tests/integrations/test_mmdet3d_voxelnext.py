"""MSSF-V (VoxelNeXt) and its radar-only twin inside the real mmdetection3d 1.4.0, on View-of-Delft and TJ4DRadSet.

Each shipped config (``mssf_voxelnext_{vod,tj4d}.py``, ``voxelnext_{vod,tj4d}_radar.py``), with the data root (the
generated VoD / TJ4DRadSet trees of test_mmdet3d_train.py / test_mmdet3d_tj4d.py), the iteration count (2), the
image scale and the widths (:func:`tiny`: a 16-32 channel encoder and head, MSDFF values of 32 channels; layout,
fusion and schedule as shipped) overridden, goes through ``Runner.from_cfg(cfg).train()``, which validates at its end
with the dataset's official protocol (``VoDMetric`` / ``TJ4DMetric``): the head's and the semantic head's losses
present and finite, every fusion parameter with a non-zero gradient, the metric's keys. The radar-only twins are the
MSSF models less the fusion, parameter for parameter; the loss falls on one frame trained over and over.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import require_mmdet3d, write_tj4d_tree, write_tree  # noqa: E402
from test_mmdet3d_train import run, small_cfg  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
PAIRS = {"vod": ("mssf_voxelnext_vod.py", "voxelnext_vod_radar.py"),
         "tj4d": ("mssf_voxelnext_tj4d.py", "voxelnext_tj4d_radar.py")}
METRIC_KEYS = {"vod": {f"VoD/{r}/{c}/AP3D_R40" for r in ("entire_area", "driving_corridor")
                       for c in ("Car", "Pedestrian", "Cyclist", "mAP")},
               "tj4d": {f"TJ4D/{r}/{c}/AP3D_R40" for r in ("range_0_50", "range_0_70", "range_all")
                        for c in ("Car", "Pedestrian", "Cyclist", "Truck", "mAP")}}


@pytest.fixture(scope="module")
def roots(tmp_path_factory):
    require_mmdet3d()
    return {"vod": write_tree(tmp_path_factory.mktemp("vod")), "tj4d": write_tj4d_tree(tmp_path_factory.mktemp("tj4d"))}


def tiny(cfg):
    """Shrink the widths (the CI budget): encoder stem / stages 8-32 channels, BEV and head 32, MSDFF values and the
    semantic head 32. The layout, the fusion blocks, the head's settings and the image branch stay as shipped."""
    enc, head = cfg.model.pts_middle_encoder, cfg.model.pts_bbox_head
    enc.update(channels=[8, 8, 16, 16, 32, 32, 32], out_channels=32)
    if enc.num_fusion_blocks:
        enc.update(msdff_value_dim=32, seg_hidden=[32, 32])
    head.update(in_channels=32, head_channels=32)
    return cfg


def _config(name, root, work_dir, iters=2):
    return tiny(small_cfg(name, root, work_dir, iters))


def check(runner, rec, dataset, fusion, batch):
    assert len(rec.losses) == 2 and rec.batch_sizes == [batch, batch]
    for step in rec.losses:
        assert {"loss_heatmap", "loss_bbox"} <= set(step) and ("loss_seg" in step) == fusion, step
        assert all(math.isfinite(v) for v in step.values()), step
    if fusion:
        assert rec.nonzero and all(rec.nonzero.values()), [n for n, ok in rec.nonzero.items() if not ok]
        assert runner.model.pts_middle_encoder.num_fusion_blocks == 2
    else:
        assert not rec.nonzero
    assert [it for it, _ in rec.validations] == [2]
    assert METRIC_KEYS[dataset] <= set(rec.validations[0][1])


@pytest.mark.parametrize("dataset,fusion", [("vod", True), ("vod", False), ("tj4d", True), ("tj4d", False)])
def test_config_trains_and_evaluates(dataset, fusion, roots, tmp_path):
    name = PAIRS[dataset][0 if fusion else 1]
    cfg = _config(name, roots[dataset], tmp_path)
    assert cfg.model.pts_bbox_head.type == "MSSFVoxelNeXtHead" and "pts_backbone" not in cfg.model
    assert cfg.model.pts_middle_encoder.layout == "VoxelResBackBone8xVoxelNeXt"
    runner, rec = run(cfg)
    check(runner, rec, dataset, fusion, batch=4 if dataset == "vod" else 2)  # (the TJ4D tree has 2 training frames)


@pytest.mark.parametrize("dataset", ["vod", "tj4d"])
def test_fusion_removed_is_the_radar_only_twin(dataset, roots, tmp_path):
    from mmdet3d.registry import MODELS
    from mmengine.registry import init_default_scope

    mssf, radar = PAIRS[dataset]
    cfg, twin = small_cfg(mssf, roots[dataset], tmp_path), small_cfg(radar, roots[dataset], tmp_path)
    cfg.model.img_backbone = None
    cfg.model.img_neck = None
    cfg.model.pts_middle_encoder.update(num_fusion_blocks=0, image_channels=None, seg_hidden=None)
    assert cfg.model == twin.model
    if dataset == "vod":  # the same weights, built with the same seed (tiny widths: the build is what is compared)
        init_default_scope("mmdet3d")
        tiny(cfg), tiny(twin)
        torch.manual_seed(0)
        a = MODELS.build(cfg.model).state_dict()
        torch.manual_seed(0)
        b = MODELS.build(twin.model).state_dict()
        assert list(a) == list(b) and all(torch.equal(a[k], b[k]) for k in a)


def test_loss_falls_on_an_overfit_frame(roots, tmp_path):
    """The VoxelNeXt detector (the radar-only twin, tiny widths: the fused model's steps cost its ResNet-50; the
    training tests above give it gradients) trained 20 times on one VoD frame (no augmentation, constant lr 3e-3):
    the box losses fall to under half their start."""
    cfg = _config(PAIRS["vod"][1], roots["vod"], tmp_path, iters=20)
    ds = cfg.train_dataloader.dataset.to_dict()
    ds["indices"] = 1
    ds["pipeline"] = [t for t in ds["pipeline"]
                      if t["type"] not in ("RandomFlip3D", "GlobalRotScaleTrans", "PointShuffle")]
    # one epoch of 20 copies: mmengine's iteration loop sleeps 2 s at every end of an epoch
    cfg.train_dataloader.update(batch_size=1, num_workers=0, persistent_workers=False)
    cfg.train_dataloader.dataset = dict(type="RepeatDataset", times=20, dataset=ds)
    cfg.optim_wrapper.optimizer.lr = 3e-3
    cfg.param_scheduler = []
    cfg.val_dataloader = cfg.val_cfg = cfg.val_evaluator = None
    cfg.test_dataloader = cfg.test_cfg = cfg.test_evaluator = None
    cfg.train_cfg = dict(type="IterBasedTrainLoop", max_iters=20)
    cfg.default_hooks.checkpoint = dict(type="CheckpointHook", interval=1000)
    _, rec = run(cfg)
    box = [s["loss_heatmap"] + s["loss_bbox"] for s in rec.losses]
    assert len(box) == 20 and all(math.isfinite(v) for v in box)
    assert sum(box[-5:]) / 5 < 0.5 * box[0], box


@pytest.mark.parametrize("authors_layout", [False, True])
def test_encoder_runs_conv_out_and_shared_conv_once(authors_layout):
    """The sparse BEV is ``shared_conv(conv_out(merged stages))``: each runs once per forward (OpenPCDet's and the
    authors' encoders), in OpenPCDet's tail (a regular ``SparseConv2d``, then the submanifold ``shared_conv``) and
    in the authors' (their biased ``shared_conv``)."""
    require_mmdet3d()
    from mssf_blocks.integrations.mmdet3d_plugin import MSSFSparseEncoder

    enc = MSSFSparseEncoder(7, [41, 128, 128], [0, -25.6, -3, 51.2, 25.6, 2], [0.4, 0.4, 0.125],
                            layout="VoxelResBackBone8xVoxelNeXt", num_fusion_blocks=0, channels=[8] * 7,
                            out_channels=8, authors_layout=authors_layout).train()
    calls = {"conv_out": 0, "shared_conv": 0}
    for name in calls:
        getattr(enc.net, name).register_forward_hook(lambda m, i, o, n=name: calls.__setitem__(n, calls[n] + 1))
    g = torch.Generator().manual_seed(0)
    coords = torch.stack([torch.randint(0, 2, (80,), generator=g), torch.randint(0, 40, (80,), generator=g),
                          torch.randint(0, 128, (80,), generator=g), torch.randint(0, 128, (80,), generator=g)], 1)
    coords = coords.unique(dim=0).int()
    (bev,) = enc(torch.randn(len(coords), 7, generator=g), coords, 2)
    assert calls == {"conv_out": 1, "shared_conv": 1}
    assert bev.indices.shape[1] == 3 and bev.features.shape[1] == 8 and list(bev.spatial_shape) == [16, 16]
