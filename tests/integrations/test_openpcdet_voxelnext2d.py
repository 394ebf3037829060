"""MSSF-VoxelNeXt-2D (``MSSFVoxelNeXt`` + ``MSSFVoxelResBackBone8xVoxelNeXt2D``) and its radar-only twin on
View-of-Delft through OpenPCDet's code (the generated tree and loops of ``test_openpcdet_vod.py``).

The references: OpenPCDet's own ``VoxelResBackBone8xVoxelNeXt2D`` (the fusion removed must equal it, weights
copied), the example ``PointPillarsBackbone``'s fusion step (what mmdet3d's ``MSSFPillarEncoder`` runs) on the
same pillar map, a naive loop for the pure-torch ``scatter_max``, and the VoD evaluation (checked against the
official kit in ``test_openpcdet_vod.py``). The backbone's widths are OpenPCDet's (fixed); the pillars are
coarsened to 0.32 m and the image branch shrunk for the CPU.
"""

from __future__ import annotations

import copy
import logging
import pickle
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
MSSF, TWIN = "mssf_voxelnext2d", "voxelnext2d_radar"


def small(name, ckpt, folder="vod_models"):
    """The shipped config, shrunk for the CPU (no setting the tests check is changed)."""
    cfg = load(name, folder)
    vs = cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE
    vs[:2] = [0.32, 0.32]  # VoD: 160 x 160 pillars (TJ4D: 216 x 248); z stays the whole range
    m = cfg.MODEL
    if "IMAGE_BRANCH" in m:
        m.IMAGE_BRANCH.update(DEPTH=18, BASE_CHANNELS=8, FPN_CHANNELS=16, CHECKPOINT=str(ckpt))
        m.BACKBONE_3D.update(IMAGE_CHANNELS=[16] * 4, MSDFF_HEADS=2, MSDFF_POINTS=2, SEG_HIDDEN=[16])
    m.DENSE_HEAD.POST_PROCESSING.NMS_CONFIG.update(NMS_PRE_MAXSIZE=256, NMS_POST_MAXSIZE=50)  # CPU NMS
    cfg.OPTIMIZATION.BATCH_SIZE_PER_GPU = 2
    return cfg


def test_pure_torch_scatter_max_equals_a_loop():
    from mssf_examples.openpcdet.scatter_ops import scatter_max

    gen = torch.Generator().manual_seed(0)
    src, index = torch.randn(50, 3, generator=gen), torch.randint(0, 9, (50,), generator=gen)
    index[index == 4] = 5  # an empty row
    out, _ = scatter_max(src, index)
    want = torch.zeros(int(index.max()) + 1, 3)
    for j in range(want.shape[0]):
        rows = src[index == j]
        if len(rows):
            want[j] = rows.max(0).values
    torch.testing.assert_close(out, want, rtol=0, atol=0)
    with pytest.raises(MSSFError, match="scatter_max: expected src"):
        scatter_max(src, index, dim=1)


def test_shipped_configs(tools):
    mssf, twin = load(MSSF), load(TWIN)
    for cfg in (mssf, twin):
        d = cfg.DATA_CONFIG
        assert d.POINT_CLOUD_RANGE == [0, -25.6, -3, 51.2, 25.6, 2]
        assert d.DATA_PROCESSOR[-1].NAME == "transform_points_to_voxels_placeholder"
        assert d.DATA_PROCESSOR[-1].VOXEL_SIZE == [0.16, 0.16, 5]  # the paper's pillars
        assert cfg.MODEL.VFE.NAME == "DynamicPillarVFESimple2D" and cfg.MODEL.VFE.NUM_FILTERS == [32]
        assert cfg.MODEL.BACKBONE_3D.NAME == "MSSFVoxelResBackBone8xVoxelNeXt2D"
        assert cfg.MODEL.DENSE_HEAD.NAME == "VoxelNeXtHead" and cfg.MODEL.DENSE_HEAD.INPUT_FEATURES == 256
    b = mssf.MODEL.BACKBONE_3D
    assert (b.NUM_FUSION_BLOCKS, b.FUSION, b.SEG_HIDDEN) == (2, "msdff", [256, 256])
    assert [a.NAME for a in mssf.DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST] == list(b.AUG_ORDER)
    stock = copy.deepcopy(mssf)
    del stock.MODEL["IMAGE_BRANCH"]
    stock.DATA_CONFIG.GET_ITEM_LIST = ["points"]
    stock.MODEL.BACKBONE_3D = type(b)(NAME=b.NAME, NUM_FUSION_BLOCKS=0)
    assert stock == twin


def _batch(loader, model, upto):
    """A loaded evaluation batch after the model's first ``upto`` modules."""
    from pcdet.models import load_data_to_gpu

    batch = next(iter(loader))
    load_data_to_gpu(batch)
    with torch.no_grad():
        for m in model.module_list[:upto]:
            batch = m(batch)
    return batch


def test_fusion_removed_equals_openpcdets_backbone(tools):
    """The backbone less its fusion = OpenPCDet's VoxelResBackBone8xVoxelNeXt2D with the same weights: the same
    sparse BEV (sites and features). Both in training mode, where OpenPCDet's conv biases (which ours leaves out,
    a BatchNorm follows each) are cancelled by the batch statistics."""
    from easydict import EasyDict
    from pcdet.models.backbones_3d.spconv_backbone_voxelnext2d import VoxelResBackBone8xVoxelNeXt2D

    torch.manual_seed(0)
    cfg = small(TWIN, tools.ckpt)
    _, loader, model = build(cfg, training=False)
    ours = model.backbone_3d
    assert model.image_branch is None and ours.num_fusion_blocks == 0
    stock = VoxelResBackBone8xVoxelNeXt2D(EasyDict(), 32, ours.sparse_shape[::-1].copy())
    with torch.no_grad():
        for p in stock.parameters():
            p.add_(torch.randn_like(p) * 0.05)
    state = stock.state_dict()
    biases = sorted(set(state) - set(ours.state_dict()))
    assert biases and all(k.endswith(".bias") and "bn" not in k for k in biases)
    assert sorted(set(ours.state_dict()) - set(state)) == []
    ours.load_state_dict({k: v for k, v in state.items() if k not in biases}, strict=True)
    batch = _batch(loader, model, 1)  # DynamicPillarVFESimple2D
    stock.train(), ours.train()
    a = stock(dict(batch))["encoded_spconv_tensor"]
    b = ours(dict(batch))["encoded_spconv_tensor"]
    assert a.indices.shape[0] > 0
    ia, ib = a.indices.long(), b.indices.long()
    oa = torch.argsort((ia[:, 0] * 10**6 + ia[:, 1]) * 10**3 + ia[:, 2])
    ob = torch.argsort((ib[:, 0] * 10**6 + ib[:, 1]) * 10**3 + ib[:, 2])
    torch.testing.assert_close(ib[ob], ia[oa], rtol=0, atol=0)
    torch.testing.assert_close(b.features[ob], a.features[oa], rtol=1e-4, atol=1e-4)


def test_fusion_equals_the_example_pointpillars_fusion_step(tools):
    """Each fusing stage = the example PointPillarsBackbone's fusion step (its own lift, fusion block, pillar
    sum and semantic head; weights copied) on the stage's pillar map made dense, read at the active pillars."""
    from mssf_examples.models.backbones import PointPillarsBackbone
    from mssf_examples.models.backbones.fusion_stage import BackboneOutput

    from mssf_blocks.voxel_grid import VoxelGrid

    torch.manual_seed(0)
    cfg = small(MSSF, tools.ckpt)
    _, loader, model = build(cfg, training=False)
    model.eval()
    bb = model.backbone_3d
    with torch.no_grad():  # off the initial values everywhere (zero-initialised attention weights included)
        for p in bb.stages.parameters():
            p.normal_(0, 0.3)
    seen = []
    fuse = bb._fuse_sparse

    def record(i, x, voxels, inputs, batch_dict):
        out = fuse(i, x, voxels, inputs, batch_dict)
        seen.append((i, x.dense(), x.indices.long(), voxels, inputs, out.features, batch_dict.get("mssf_seg_logits")))
        return out

    bb._fuse_sparse = record
    with torch.no_grad():
        _batch(loader, model, len(model.module_list))
    assert [s[0] for s in seen] == [0, 1]
    pcr, vs = cfg.DATA_CONFIG.POINT_CLOUD_RANGE, cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE
    ref = PointPillarsBackbone(7, VoxelGrid(voxel_size=tuple(vs), point_cloud_range=tuple(pcr)), lift_z_size=0.125,
                               pfn_channels=32, layer_nums=(1, 1), layer_strides=(1, 2), num_filters=(32, 64),
                               upsample_strides=(1, 2), num_upsample_filters=(8, 8), num_fusion_blocks=2,
                               image_channels=[16] * 4, msdff_heads=2, msdff_points=2, seg_hidden=(16,))
    mapped = {}
    for k, v in bb.stages.state_dict().items():
        i, part, rest = k.split(".", 2)
        mapped[f"lifts.{i}.{rest}" if part == "lift" else f"seg_head.{rest[len('semantic_head.'):]}"
               if rest.startswith("semantic_head.") else f"fusions.{i}.{rest}"] = v
    missing, unexpected = ref.load_state_dict(mapped, strict=False)
    assert not unexpected and all(k.split(".")[0] in ("pfn", "down", "convs", "deblocks") for k in missing)
    ref.eval()
    with torch.no_grad():
        for i, dense, idx, voxels, inputs, got, logits in seen:
            out = BackboneOutput(stages=[])
            want = ref._fuse(i, dense, voxels, inputs, out)[idx[:, 0], :, idx[:, 1], idx[:, 2]]
            assert voxels.coords.shape[0] > 0
            torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
            if i == 1:
                torch.testing.assert_close(logits, out.seg_logits, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", [MSSF, TWIN])
def test_trains_through_openpcdet_then_evaluates_with_the_vod_protocol(tools, tmp_path, name):
    from eval_utils.eval_utils import eval_one_epoch
    from pcdet.datasets import build_dataloader

    torch.manual_seed(0)
    cfg = small(name, tools.ckpt)
    cfg.MODEL.DENSE_HEAD.POST_PROCESSING.SCORE_THRESH = 0.0  # a barely trained head: keep its boxes
    _, loader, model = build(cfg)
    seen = train(cfg, model, loader)
    assert len(seen) == len(loader) >= 2
    if name == MSSF:
        assert model.module_list[0] is model.image_branch and model.backbone_3d.num_fusion_blocks == 2
        for loss, tb in seen:
            assert np.isfinite(loss) and tb["loss_mssf_seg"] > 0 and np.isfinite(tb["loss_mssf_seg"])
        no_grad = [n for n, p in model.backbone_3d.stages.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
        assert not no_grad, no_grad
    else:
        assert model.image_branch is None and all(np.isfinite(loss) and "loss_mssf_seg" not in tb for loss, tb in seen)
    _, val_loader, _ = build_dataloader(cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=2, dist=False, workers=0,
                                        training=False)
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, val_loader, epoch_id="1", logger=logging.getLogger("eval"),
                         result_dir=tmp_path)
    for region in ("entire_area", "driving_corridor"):
        assert f"{region}/mAP3D_R40" in ret and f"{region}/Car_AP3D_R40" in ret
    with open(tmp_path / "result.pkl", "rb") as f:
        dets = pickle.load(f)
    assert len(dets) == 2 and sum(len(d["name"]) for d in dets) > 0


def test_overfit_lowers_the_loss(tools):
    torch.manual_seed(0)
    first, last = overfit(small(MSSF, tools.ckpt), epochs=8)
    assert last < 0.6 * first, (first, last)


def test_config_errors_name_the_key(tools):
    cfg = small(MSSF, tools.ckpt)
    bad = copy.deepcopy(cfg)
    bad.MODEL.VFE.NUM_FILTERS = [16]
    with pytest.raises(MSSFError, match="MODEL.VFE.NUM_FILTERS: .* takes 32 pillar channels, the VFE gives 16"):
        build(bad)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_3D.CHANNELS = [64] * 6  # the stock widths are fixed
    with pytest.raises(MSSFError, match=r"MODEL.BACKBONE_3D: unknown keys \['CHANNELS'\]"):
        build(bad)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_3D.NUM_FUSION_BLOCKS = 7
    with pytest.raises(MSSFError, match=r"MODEL.BACKBONE_3D.NUM_FUSION_BLOCKS: expected an int in \[0, 6\]"):
        build(bad)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_3D.IMAGE_CHANNELS = [16, 16]
    with pytest.raises(MSSFError, match="MODEL.BACKBONE_3D.IMAGE_CHANNELS"):
        build(bad)


def test_documented_commands_run_openpcdet_train_py(tools, monkeypatch):
    """docs/frameworks.md's VoxelNeXt-2D commands, from tools/, with CPU sizes through train.py's own options:
    OpenPCDet's train.py trains each model one epoch, saves a checkpoint and evaluates it (VoD evaluation)."""
    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.openpcdet.__main__ import main
    from test_openpcdet_pointpillar import documented_commands

    monkeypatch.setattr("time.sleep", lambda seconds: None)  # repeat_eval_ckpt waits 30 s for new checkpoints
    ckpt = tools.root.parent / "checkpoints" / "htc_r50_fpn_image_branch.pth"  # the config's CHECKPOINT
    ckpt.parent.mkdir(exist_ok=True)
    torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=256, num_outs=4).state_dict(), ckpt)
    commands = documented_commands("VoxelNeXt-2D")
    assert [c[:3] for c in commands] == [["train.py", "--cfg_file", f"cfgs/vod_models/{n}.yaml"] for n in (MSSF, TWIN)]
    image = ["MODEL.IMAGE_BRANCH.DEPTH", "18", "MODEL.IMAGE_BRANCH.BASE_CHANNELS", "8",
             "MODEL.BACKBONE_3D.MSDFF_HEADS", "2", "MODEL.BACKBONE_3D.SEG_HIDDEN", "[16]"]
    for argv, name in zip(commands, (MSSF, TWIN)):
        cpu = ["--epochs", "1", "--workers", "0", "--extra_tag", "cpu_test", "--batch_size", "2", "--wo_gpu_stat",
               "--set", "OPTIMIZATION.PCT_START", "0.5", *(image if name == MSSF else [])]
        main(["--pure-torch-nms", *argv, *cpu])
        out = tools.root.parent / "output" / "vod_models" / name / "cpu_test"
        assert (out / "ckpt" / "checkpoint_epoch_1.pth").is_file()
        log = "".join(p.read_text() for p in out.glob("*.log"))
        assert "VoD entire_area:" in log and "VoD driving_corridor:" in log, log[-2000:]
