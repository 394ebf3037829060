"""MSSF-PP (``MSSFPointPillar`` + ``MSSFBaseBEVBackbone``) and its radar-only twin (OpenPCDet's own
``PointPillar``) on View-of-Delft through OpenPCDet's code.

The generated VoD tree, the configs copied into ``tools/cfgs`` and OpenPCDet's loops come from
``test_openpcdet_vod.py`` (its ``tools`` fixture and helpers). The references: OpenPCDet's stock
``PointPillar`` / ``BaseBEVBackbone`` (the fusion removed must equal it, weights copied), the example
``PointPillarsBackbone`` that mmdet3d's ``MSSFPillarEncoder`` runs (the same fusion on the same BEV map,
weights copied), the mmdet3d MSSF-PP config (pillar size, range, anchors) and the official VoD evaluation
(``test_vod_evaluation_equals_the_official_kit`` checks ``dataset.evaluation`` against the kit).
Sizes are shrunk for the CPU (pillars of 0.32 m, narrow layers, a ResNet-18 of width 8).
"""

from __future__ import annotations

import copy
import logging
import pickle
import runpy
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
# test_openpcdet_vod's loops and its tools fixture (the generated VoD tree; module scope: this module gets its own)
from openpcdet_models import build, load, overfit, tools, train  # noqa: E402,F401  (tools: fixture)

from mssf_blocks import MSSFError  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
MSSF, TWIN = "mssf_pointpillar", "pointpillar_radar"
MMDET3D_MODEL = Path(__file__).resolve().parents[2] / "examples" / "configs" / "mmdet3d" / "_base_" / "models" / \
    "mssf_pointpillars_vod.py"


def small(name, ckpt, folder="vod_models"):
    """The shipped config, shrunk for the CPU (no setting the tests check is changed)."""
    cfg = load(name, folder)
    vs = cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE
    vs[:2] = [0.32, 0.32]  # VoD: 160 x 160 pillars (TJ4D: 216 x 248); z stays the whole range
    m = cfg.MODEL
    m.VFE.NUM_FILTERS = [16]
    m.MAP_TO_BEV.NUM_BEV_FEATURES = 16
    m.BACKBONE_2D.update(LAYER_NUMS=[1, 1, 1], NUM_FILTERS=[16, 32, 32], NUM_UPSAMPLE_FILTERS=[16, 16, 16])
    if "IMAGE_BRANCH" in m:
        m.IMAGE_BRANCH.update(DEPTH=18, BASE_CHANNELS=8, FPN_CHANNELS=16, CHECKPOINT=str(ckpt))
        m.BACKBONE_2D.update(IMAGE_CHANNELS=[16] * 4, MSDFF_HEADS=2, MSDFF_POINTS=2, SEG_HIDDEN=[16])
    cfg.OPTIMIZATION.BATCH_SIZE_PER_GPU = 2
    return cfg


def radar_only(cfg):
    """The MSSF-PP config with its fusion removed: no fusion blocks, no image branch, no images read."""
    cfg = copy.deepcopy(cfg)
    cfg.MODEL.BACKBONE_2D.NUM_FUSION_BLOCKS = 0
    del cfg.MODEL["IMAGE_BRANCH"]
    cfg.DATA_CONFIG.GET_ITEM_LIST = ["points"]
    return cfg


def test_shipped_configs_have_the_paper_pillar_settings(tools):
    mm = runpy.run_path(str(MMDET3D_MODEL))
    enc, head = mm["model"]["pts_middle_encoder"], mm["model"]["pts_bbox_head"]
    mssf, twin = load(MSSF), load(TWIN)
    for cfg in (mssf, twin):
        d = cfg.DATA_CONFIG
        assert d.POINT_CLOUD_RANGE == enc["point_cloud_range"] == [0, -25.6, -3, 51.2, 25.6, 2]
        assert d.DATA_PROCESSOR[-1].VOXEL_SIZE == enc["voxel_size"] == [0.16, 0.16, 5]
        assert len(d.POINT_FEATURE_ENCODING.used_feature_list) == enc["in_channels"] == 7
        m = cfg.MODEL
        assert m.VFE.NAME == "PillarVFE" and m.VFE.NUM_FILTERS == [enc["pfn_channels"]]
        assert m.MAP_TO_BEV.NAME == "PointPillarScatter" and m.DENSE_HEAD.NAME == "AnchorHeadSingle"
        b = m.BACKBONE_2D
        assert (b.LAYER_NUMS, b.LAYER_STRIDES, b.NUM_FILTERS, b.UPSAMPLE_STRIDES, b.NUM_UPSAMPLE_FILTERS) == (
            enc["layer_nums"], enc["layer_strides"], enc["num_filters"], enc["upsample_strides"],
            enc["num_upsample_filters"])
        anchors = m.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG
        assert [a["class_name"] for a in anchors] == cfg.CLASS_NAMES == ["Car", "Pedestrian", "Cyclist"]
        assert [a["anchor_sizes"][0] for a in anchors] == head["anchor_generator"]["sizes"]
        assert [a["anchor_bottom_heights"][0] for a in anchors] == [r[2] for r in head["anchor_generator"]["ranges"]]
        assert all(a["anchor_rotations"] == head["anchor_generator"]["rotations"] for a in anchors)
        assert all(a["feature_map_stride"] == b.LAYER_STRIDES[0] // b.UPSAMPLE_STRIDES[0] for a in anchors)
    b = mssf.MODEL.BACKBONE_2D
    assert (b.NUM_FUSION_BLOCKS, b.FUSION, b.FUSION_POSITION, b.LIFT_Z_SIZE, b.SEG_HIDDEN) == (
        enc["num_fusion_blocks"], enc["fusion"], enc["fusion_position"], enc["lift_z_size"], enc["seg_hidden"])
    assert [a.NAME for a in mssf.DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST] == list(b.AUG_ORDER)
    assert mssf.MODEL.IMAGE_BRANCH.FROZEN is True and "images" in mssf.DATA_CONFIG.GET_ITEM_LIST
    # the twin: the same config less the image branch, the fusion keys and the images
    stock = radar_only(mssf)
    for k in [k for k in stock.MODEL.BACKBONE_2D if k not in twin.MODEL.BACKBONE_2D and k != "NAME"]:
        del stock.MODEL.BACKBONE_2D[k]
    stock.MODEL.NAME, stock.MODEL.BACKBONE_2D.NAME = "PointPillar", "BaseBEVBackbone"
    assert stock == twin


@pytest.mark.parametrize("name", [MSSF, TWIN])
def test_trains_through_openpcdet_then_evaluates_with_the_vod_protocol(tools, tmp_path, name):
    """train_one_epoch (2 steps), then eval_one_epoch with the dataset's VoD evaluation, of the trained model."""
    from eval_utils.eval_utils import eval_one_epoch
    from pcdet.datasets import build_dataloader

    torch.manual_seed(0)
    cfg = small(name, tools.ckpt)
    cfg.MODEL.POST_PROCESSING.SCORE_THRESH = 0.0  # a barely trained head: keep its boxes
    cfg.MODEL.POST_PROCESSING.NMS_CONFIG.update(NMS_PRE_MAXSIZE=256, NMS_POST_MAXSIZE=50)  # CPU NMS, CPU evaluation
    _, loader, model = build(cfg)
    seen = train(cfg, model, loader)
    assert len(seen) == len(loader) >= 2
    if name == MSSF:
        assert model.module_list[0] is model.image_branch and model.image_branch.branch.frozen
        assert type(model.backbone_2d).__name__ == "MSSFBaseBEVBackbone" and model.backbone_2d.num_fusion_blocks == 2
        for loss, tb in seen:
            assert np.isfinite(loss) and tb["loss_mssf_seg"] > 0 and np.isfinite(tb["loss_mssf_seg"])
            assert loss == pytest.approx(tb["loss_rpn"] + tb["loss_mssf_seg"], rel=1e-5)
        fusion = list(model.backbone_2d.stages.named_parameters())
        assert len(fusion) > 10
        no_grad = [n for n, p in fusion if p.grad is None or not p.grad.abs().sum() > 0]
        assert not no_grad, no_grad
        assert all(p.grad is None for p in model.image_branch.parameters())  # frozen
    else:
        assert type(model).__name__ == "PointPillar"  # OpenPCDet's own
        assert all(np.isfinite(loss) and "loss_mssf_seg" not in tb for loss, tb in seen)
    _, val_loader, _ = build_dataloader(cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=2, dist=False, workers=0,
                                        training=False)
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, val_loader, epoch_id="1", logger=logging.getLogger("eval"),
                         result_dir=tmp_path)
    for region in ("entire_area", "driving_corridor"):
        assert f"{region}/mAP3D_R40" in ret and f"{region}/Car_AP3D_R40" in ret
    assert "recall/roi_0.3" in ret
    with open(tmp_path / "result.pkl", "rb") as f:
        dets = pickle.load(f)
    assert len(dets) == 2 and sum(len(d["name"]) for d in dets) > 0
    assert ret["entire_area/mAP3D_R40"] == pytest.approx(np.mean([ret[f"entire_area/{c}_AP3D_R40"] for c in cfg.CLASS_NAMES]))


def test_overfit_lowers_the_loss(tools):
    torch.manual_seed(0)
    first, last = overfit(small(MSSF, tools.ckpt), "BACKBONE_2D")
    assert last < 0.6 * first, (first, last)


def _eval_batch(loader):
    from pcdet.models import load_data_to_gpu

    batch = next(iter(loader))
    load_data_to_gpu(batch)
    return batch


def test_fusion_removed_equals_openpcdets_pointpillar(tools):
    """MSSF-PP less its fusion (NUM_FUSION_BLOCKS 0, no image branch) = OpenPCDet's stock PointPillar
    (pointpillar_radar.yaml) with the same weights: the same parameters, the same head outputs and boxes."""
    torch.manual_seed(0)
    twin, fused = small(TWIN, tools.ckpt), radar_only(small(MSSF, tools.ckpt))
    for cfg in (twin, fused):
        cfg.MODEL.POST_PROCESSING.SCORE_THRESH = 0.0  # boxes to compare
        cfg.MODEL.POST_PROCESSING.NMS_CONFIG.update(NMS_PRE_MAXSIZE=256, NMS_POST_MAXSIZE=50)  # CPU NMS
    _, loader, stock = build(twin, training=False)
    _, _, ours = build(fused, training=False)
    assert type(stock).__name__ == "PointPillar" and type(stock.backbone_2d).__name__ == "BaseBEVBackbone"
    assert type(ours).__name__ == "MSSFPointPillar" and ours.image_branch is None
    assert list(ours.state_dict()) == list(stock.state_dict())
    with torch.no_grad():  # BatchNorm statistics off their defaults, so a wrong layer order would show
        for p in stock.parameters():
            p.add_(torch.randn_like(p) * 0.02)
        for mod in stock.modules():
            if isinstance(mod, (torch.nn.BatchNorm1d, torch.nn.BatchNorm2d)):
                mod.running_mean.normal_(0, 0.1)
                mod.running_var.uniform_(0.5, 1.5)
    ours.load_state_dict(stock.state_dict(), strict=True)
    stock.eval(), ours.eval()
    batch = _eval_batch(loader)
    with torch.no_grad():
        a, _ = stock(copy.deepcopy(batch))
        b, _ = ours(copy.deepcopy(batch))
        da, db = stock.dense_head.forward_ret_dict, ours.dense_head.forward_ret_dict
    for key in ("cls_preds", "box_preds", "dir_cls_preds"):
        torch.testing.assert_close(db[key], da[key], rtol=0, atol=0)
    assert sum(len(p["pred_boxes"]) for p in a) > 0
    for pa, pb in zip(a, b):
        for key in ("pred_boxes", "pred_scores", "pred_labels"):
            torch.testing.assert_close(pb[key], pa[key], rtol=0, atol=0)


@pytest.mark.parametrize("fusion, position", [("msdff", "before_residual"), ("sff", "after_residual")])
def test_fusion_equals_the_example_pointpillars_backbone(tools, fusion, position):
    """MSSFBaseBEVBackbone's fusion = the example PointPillarsBackbone's (what mmdet3d's MSSFPillarEncoder
    runs: its own lift voxels, fusion blocks, pillar sum and semantic head) on the same scattered pillar
    features and the same camera inputs, weights copied: the same BEV map and seg logits."""
    from mssf_examples.models.backbones import PointPillarsBackbone

    from mssf_blocks.integrations._common import points_with_batch
    from mssf_blocks.integrations.openpcdet import fusion_inputs_from_batch_dict
    from mssf_blocks.sparse_voxels import SparseVoxels
    from mssf_blocks.voxel_grid import VoxelGrid

    torch.manual_seed(0)
    cfg = small(MSSF, tools.ckpt)
    cfg.MODEL.BACKBONE_2D.update(FUSION=fusion, FUSION_POSITION=position)
    _, loader, model = build(cfg, training=False)
    model.eval()
    batch = _eval_batch(loader)
    with torch.no_grad():
        for m in model.module_list[:3]:  # image branch, PillarVFE, PointPillarScatter
            batch = m(batch)
    bb, b2 = model.backbone_2d, cfg.MODEL.BACKBONE_2D
    pcr, vs = cfg.DATA_CONFIG.POINT_CLOUD_RANGE, cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE
    grid = VoxelGrid(voxel_size=tuple(vs), point_cloud_range=tuple(pcr))
    ref = PointPillarsBackbone(7, grid, lift_z_size=b2.LIFT_Z_SIZE, pfn_channels=16, layer_nums=b2.LAYER_NUMS,
                               layer_strides=b2.LAYER_STRIDES, num_filters=b2.NUM_FILTERS,
                               upsample_strides=b2.UPSAMPLE_STRIDES, num_upsample_filters=b2.NUM_UPSAMPLE_FILTERS,
                               num_fusion_blocks=2, fusion=fusion, fusion_position=position,
                               image_channels=[16] * 4, msdff_heads=2, msdff_points=2,
                               seg_hidden=(16,))
    with torch.no_grad():  # off the initial values everywhere (zero-initialised attention weights included)
        for p in bb.parameters():
            p.normal_(0, 0.3)
    mapped = {}
    for k, v in bb.state_dict().items():
        parts = k.split(".")
        if parts[0] == "blocks":
            i, j = int(parts[1]), int(parts[2])
            k = ".".join(["down", str(i), str(j)] if j < 4 else ["convs", str(i), str(j - 4)]) + "." + ".".join(parts[3:])
        elif parts[0] == "stages":
            rest = ".".join(parts[3:])
            k = (f"lifts.{parts[1]}.{rest}" if parts[2] == "lift" else
                 f"seg_head.{'.'.join(parts[4:])}" if parts[3] == "semantic_head" else f"fusions.{parts[1]}.{rest}")
        mapped[k] = v
    ref.pfn = None  # the pillar features are OpenPCDet's (PillarVFE), scattered by the reference itself
    ref.load_state_dict(mapped, strict=True)
    ref.eval()

    class OpenPCDetPillars(torch.nn.Module):
        grid = VoxelGrid(voxel_size=tuple(vs), point_cloud_range=tuple(pcr))  # the reference voxelises on it

        def forward(self, points, points_batch, batch_size, voxelization=None):
            return SparseVoxels(batch["pillar_features"], batch["voxel_coords"].int(), batch_size=batch_size, grid=grid)

    ref.pfn = OpenPCDetPillars()
    points, pb = points_with_batch(batch["points"], "points")
    inputs = fusion_inputs_from_batch_dict(batch, **bb.adapter_kwargs)
    with torch.no_grad():
        expected = ref(points, pb, int(batch["batch_size"]), inputs)
        batch = bb(batch)
    assert batch["spatial_features"].abs().sum() > 0 and expected.seg_logits.numel() > 0
    torch.testing.assert_close(batch["spatial_features_2d"], expected.bev, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(batch["mssf_seg_logits"], expected.seg_logits, rtol=1e-5, atol=1e-5)


def test_config_errors_name_the_key(tools):
    from mssf_examples.openpcdet.bev_backbone import MSSFBaseBEVBackbone
    from mssf_examples.openpcdet.detectors import check_mssf_config

    cfg = small(MSSF, tools.ckpt)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_2D.IMAGE_CHANNELS = [16, 16]
    with pytest.raises(MSSFError, match=r"MODEL.BACKBONE_2D.IMAGE_CHANNELS: .*FPN_CHANNELS 16"):
        check_mssf_config(bad.MODEL, bad.DATA_CONFIG, "BACKBONE_2D")
    bad = copy.deepcopy(cfg)
    bad.DATA_CONFIG.GET_ITEM_LIST = ["points"]
    with pytest.raises(MSSFError, match=r"DATA_CONFIG.GET_ITEM_LIST: .*MODEL.BACKBONE_2D.NUM_FUSION_BLOCKS"):
        build(bad)  # through OpenPCDet's build_network: the detector raises
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_2D.AUG_ORDER = ["random_world_rotation", "random_world_flip", "random_world_scaling"]
    with pytest.raises(MSSFError, match="MODEL.BACKBONE_2D.AUG_ORDER.*AUG_CONFIG_LIST"):
        build(bad)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_2D.NAME = "BaseBEVBackbone"  # OpenPCDet's would ignore the fusion keys
    with pytest.raises(MSSFError, match="MODEL.BACKBONE_2D.NAME: NUM_FUSION_BLOCKS 2 needs MSSFBaseBEVBackbone"):
        build(bad)
    b2 = cfg.MODEL.BACKBONE_2D
    grid = {"voxel_size": [0.32, 0.32, 5], "point_cloud_range": [0, -25.6, -3, 51.2, 25.6, 2]}
    for key, value, match in (("NUM_FUSION_BLOCK", 2, r"MODEL.BACKBONE_2D: unknown keys \['NUM_FUSION_BLOCK'\]"),
                              ("NUM_FUSION_BLOCKS", 4, r"NUM_FUSION_BLOCKS: expected an int in \[0, 3\].*got 4"),
                              ("FUSION_POSITION", "middle", "MODEL.BACKBONE_2D.FUSION_POSITION"),
                              ("FUSION", "concat", "MODEL.BACKBONE_2D.FUSION: expected 'msdff' or 'sff'"),
                              ("IMAGE_CHANNELS", None, "MODEL.BACKBONE_2D.IMAGE_CHANNELS: required")):
        bad = copy.deepcopy(b2)
        bad[key] = value
        with pytest.raises(MSSFError, match=match):
            MSSFBaseBEVBackbone(bad, 16, **grid)
    z_size = r"VOXEL_SIZE: a pillar spans the whole z range 5 m \(POINT_CLOUD_RANGE\), got z size 0.125"
    with pytest.raises(MSSFError, match=z_size):
        MSSFBaseBEVBackbone(b2, 16, voxel_size=[0.32, 0.32, 0.125], point_cloud_range=grid["point_cloud_range"])
    with pytest.raises(MSSFError, match="voxel_size, point_cloud_range: required"):
        MSSFBaseBEVBackbone(b2, 16)


def documented_commands(section="MSSF-PP (PointPillars)"):
    """The ``python -m mssf_examples.openpcdet`` lines of a docs/frameworks.md section (``### <section>``), as argv."""
    import re
    import shlex

    text = (Path(__file__).resolve().parents[2] / "docs" / "frameworks.md").read_text()
    section = text.split(f"### {section}\n", 1)[1].split("\n### ", 1)[0]
    lines = [line for block in re.findall(r"```bash\n(.*?)```", section, flags=re.DOTALL) for line in block.splitlines()]
    return [shlex.split(line)[3:] for line in lines if line.startswith("python -m mssf_examples.openpcdet ")]


def test_documented_commands_run_openpcdet_train_py(tools, monkeypatch):
    """The section's commands, from tools/, with CPU sizes through train.py's own options: OpenPCDet's train.py
    trains each model one epoch, saves a checkpoint and evaluates it with the VoD evaluation."""
    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.openpcdet.__main__ import main

    monkeypatch.setattr("time.sleep", lambda seconds: None)  # repeat_eval_ckpt waits 30 s for new checkpoints
    ckpt = tools.root.parent / "checkpoints" / "htc_r50_fpn_image_branch.pth"  # the config's CHECKPOINT
    ckpt.parent.mkdir(exist_ok=True)
    torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=256, num_outs=4).state_dict(), ckpt)
    commands = documented_commands()
    assert [c[:3] for c in commands] == [["train.py", "--cfg_file", f"cfgs/vod_models/{n}.yaml"] for n in (MSSF, TWIN)]
    narrow = ["MODEL.VFE.NUM_FILTERS", "[16]", "MODEL.MAP_TO_BEV.NUM_BEV_FEATURES", "16",
              "MODEL.BACKBONE_2D.LAYER_NUMS", "[1,1,1]", "MODEL.BACKBONE_2D.NUM_FILTERS", "[16,32,32]",
              "MODEL.BACKBONE_2D.NUM_UPSAMPLE_FILTERS", "[16,16,16]", "OPTIMIZATION.PCT_START", "0.5"]
    image = ["MODEL.IMAGE_BRANCH.DEPTH", "18", "MODEL.IMAGE_BRANCH.BASE_CHANNELS", "8",
             "MODEL.BACKBONE_2D.MSDFF_HEADS", "2", "MODEL.BACKBONE_2D.SEG_HIDDEN", "[16]"]
    for argv, name in zip(commands, (MSSF, TWIN)):
        cpu = ["--epochs", "1", "--workers", "0", "--extra_tag", "cpu_test", "--batch_size", "2", "--wo_gpu_stat",
               "--set", *narrow, *(image if name == MSSF else [])]
        main(["--pure-torch-nms", *argv, *cpu])
        out = tools.root.parent / "output" / "vod_models" / name / "cpu_test"
        assert (out / "ckpt" / "checkpoint_epoch_1.pth").is_file()
        log = "".join(p.read_text() for p in out.glob("*.log"))
        assert "VoD entire_area:" in log and "VoD driving_corridor:" in log, log[-2000:]
