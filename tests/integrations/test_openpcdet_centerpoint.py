"""MSSF-CenterPoint in OpenPCDet on View-of-Delft (``vod_models/mssf_centerpoint.yaml`` and its radar-only twin),
and for every detector kind: the fusion removed is the radar-only twin.

The VoD tree, the CPU set-up and the shrunk configs are test_openpcdet_vod.py's (its module fixture ``tools``).
MSSF-CenterPoint trains through OpenPCDet's ``train_one_epoch`` (semantic loss present, every fusion parameter
with a gradient, the frozen image branch without), evaluates through ``eval_one_epoch`` with the VoD protocol,
and its loss falls on an overfit pair of frames. The twins: the MSSF config with ``NUM_FUSION_BLOCKS: 0``, no
``IMAGE_BRANCH`` and no image read is the shipped radar-only config, key for key; built by OpenPCDet's
``build_network``, the twin takes the fusion-less model's ``state_dict`` strictly and gives the same boxes.
"""

from __future__ import annotations

import copy
import logging
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
from test_openpcdet_vod import CONFIGS, build, load, overfit, small, tools, train  # noqa: E402,F401  (tools: the module fixture)

pytestmark = pytest.mark.usefixtures("one_thread")
#: the MSSF configs and their radar-only twins
TWINS = {"mssf_second": "second_radar", "mssf_voxelnext": "voxelnext_radar", "mssf_centerpoint": "centerpoint_radar"}


def test_mssf_centerpoint_is_openpcdets_centerpoint_with_fusion(tools):
    from pcdet.models.backbones_2d import BaseBEVBackbone
    from pcdet.models.backbones_2d.map_to_bev import HeightCompression
    from pcdet.models.backbones_3d.vfe import MeanVFE
    from pcdet.models.dense_heads import CenterHead
    from pcdet.models.detectors.centerpoint import CenterPoint

    from mssf_blocks.integrations.openpcdet_backbones import MSSFVoxelResBackBone8x

    cfg = load("mssf_centerpoint")
    assert cfg.MODEL.BACKBONE_3D.NUM_FUSION_BLOCKS == 2 and cfg.MODEL.BACKBONE_3D.FUSION == "msdff"
    assert cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE == load("mssf_second").DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE
    _, _, model = build(small("mssf_centerpoint", tools.ckpt), training=False)
    assert isinstance(model, CenterPoint)
    kinds = [type(m) for m in model.module_list]
    assert kinds[0] is type(model.image_branch)
    assert kinds[1:] == [MeanVFE, MSSFVoxelResBackBone8x, HeightCompression, BaseBEVBackbone, CenterHead]


def test_mssf_centerpoint_trains_and_evaluates(tools, tmp_path):
    from eval_utils.eval_utils import eval_one_epoch

    torch.manual_seed(0)
    cfg = small("mssf_centerpoint", tools.ckpt)
    _, loader, model = build(cfg)
    seen = train(cfg, model, loader)
    assert len(seen) == len(loader) >= 2
    for loss, tb in seen:
        assert np.isfinite(loss) and tb["loss_mssf_seg"] > 0 and np.isfinite(tb["loss_rpn"])
    fusion = [(n, p) for n, p in model.backbone_3d.named_parameters() if ".fusion." in n]
    assert len(fusion) > 10
    assert not [n for n, p in fusion if p.grad is None or not p.grad.abs().sum() > 0]
    assert all(p.grad is None for p in model.image_branch.parameters())  # frozen
    _, test_loader, _ = build(keep_all_boxes(cfg), training=False)
    model.eval()
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, test_loader, epoch_id="0", logger=logging.getLogger("eval"),
                         result_dir=tmp_path)
    for region in ("entire_area", "driving_corridor"):
        assert f"{region}/mAP3D_R40" in ret and f"{region}/Cyclist_AP3D_R40" in ret
    dets = __import__("pickle").load(open(tmp_path / "result.pkl", "rb"))
    assert len(dets) == 2 and sum(len(d["name"]) for d in dets) > 0


def test_centerpoint_radar_twin_trains_without_images(tools):
    cfg = small("centerpoint_radar", tools.ckpt)
    _, loader, model = build(cfg)
    assert model.image_branch is None
    seen = train(cfg, model, loader)
    assert all(np.isfinite(loss) and "loss_mssf_seg" not in tb for loss, tb in seen)


def test_mssf_centerpoint_overfit_lowers_the_loss(tools):
    torch.manual_seed(0)
    first, last = overfit(small("mssf_centerpoint", tools.ckpt))
    assert last < 0.6 * first, (first, last)


def keep_all_boxes(cfg):
    """SCORE_THRESH 0 (an untrained head scores low), where the detector reads it."""
    post = cfg.MODEL.DENSE_HEAD.get("POST_PROCESSING", None) or cfg.MODEL.POST_PROCESSING
    post.SCORE_THRESH = 0.0
    return cfg


def fusion_removed(cfg):
    """The MSSF config less its fusion: no fusion block, no image branch, no image read."""
    cfg = copy.deepcopy(cfg)
    cfg.MODEL.BACKBONE_3D.NUM_FUSION_BLOCKS = 0
    cfg.MODEL.pop("IMAGE_BRANCH")
    cfg.DATA_CONFIG.GET_ITEM_LIST = ["points"]
    return cfg


@pytest.mark.parametrize("folder", ["vod_models", "tj4d_models"])
@pytest.mark.parametrize("name", sorted(TWINS))
def test_fusion_removed_is_the_radar_only_twin_config(tools, name, folder):
    if folder == "tj4d_models":  # (test_openpcdet_vod's fixture copies vod_models only)
        shutil.copytree(CONFIGS / folder, tools.root / "cfgs" / folder, dirs_exist_ok=True)
    assert fusion_removed(load(name, folder)) == load(TWINS[name], folder)


@pytest.mark.parametrize("name", sorted(TWINS))
def test_fusion_removed_model_equals_the_twin(tools, name):
    """Built by OpenPCDet: the same parameter names and shapes; the twin loads the fusion-less model's state_dict
    strictly and gives the same boxes and scores on the validation frames."""
    torch.manual_seed(0)
    _, loader, mine = build(keep_all_boxes(fusion_removed(small(name, tools.ckpt))), training=False)
    twin_cfg = keep_all_boxes(small(TWINS[name], tools.ckpt))
    torch.manual_seed(1)  # other initial weights: the copy must make them equal
    _, _, twin = build(twin_cfg, training=False)
    shapes = {k: v.shape for k, v in mine.state_dict().items()}
    assert shapes == {k: v.shape for k, v in twin.state_dict().items()}
    twin.load_state_dict(mine.state_dict(), strict=True)
    mine.eval(), twin.eval()
    from pcdet.models import load_data_to_gpu

    batch = next(iter(loader))
    load_data_to_gpu(batch)
    with torch.no_grad():
        a, _ = mine(copy.deepcopy(batch))
        b, _ = twin(copy.deepcopy(batch))
    assert sum(len(p["pred_boxes"]) for p in a) > 0
    for pa, pb in zip(a, b):
        for key in ("pred_boxes", "pred_scores", "pred_labels"):
            torch.testing.assert_close(pa[key], pb[key], rtol=0, atol=0)
