"""The MSSF authors' MSSF-V checkpoint (``EricLiuhhh/MSSF``, mmdet3d) into the mmdet3d MSSF-V built as theirs
(``mssf_voxelnext_vod_authors.py``): their key list, written out from their configs
(``vx_mm_r50_ablation_n2m4`` on ``voxelnext_voxel005_vod_multimodal_r50pytorch``: tests/examples/models/
test_authors_checkpoint.py's ``their_mssf_v_shapes``; no download), filled with seeded values, converts with every
tensor mapped or ignored for a reason and nothing missing, and loads with ``strict=True``; the values land where the
name rules say (their heatmap classes permuted to the config's order), and mmdet3d's ``test_step`` runs the loaded
model on a generated VoD frame (the authors' encoder, five FPN levels, their head) to ``LiDARInstance3DBoxes``."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(Path(__file__).parents[1] / "examples" / "models"))
from mmdet3d_vod_tree import CONFIGS, require_mmdet3d, write_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


def _finite(ckpt):
    """Seeded values that stay finite through the whole network: variances positive, weights of unit gain."""
    sd = ckpt["state_dict"]
    for k, v in sd.items():
        if k.endswith("running_var"):
            sd[k] = v.abs() + 0.5
        elif v.dim() >= 2:
            sd[k] = v / (v.numel() / v.shape[0]) ** 0.5
    return ckpt


def test_their_mssf_v_checkpoint_loads_strictly_into_the_authors_config(tmp_path):
    require_mmdet3d()
    import mssf_examples.mmdet3d.plugin  # noqa: F401
    from mmdet3d.registry import MODELS
    from mmengine.config import Config
    from mmengine.registry import init_default_scope
    from mssf_examples.mmdet3d.authors_mssf_v import convert_authors_mssf_v
    from test_authors_checkpoint import random_checkpoint, their_mssf_v_shapes

    from mssf_blocks.errors import MSSFError

    cfg = Config.fromfile(str(CONFIGS / "mssf_voxelnext_vod_authors.py"))
    init_default_scope("mmdet3d")
    model = MODELS.build(cfg.model)
    ckpt = _finite(random_checkpoint(their_mssf_v_shapes(), seed=3))
    theirs = ckpt["state_dict"]
    sd, report = convert_authors_mssf_v(ckpt, model, cfg.class_names)
    assert report.missing == [] and len(report.mapped) + len(report.ignored) == len(theirs)
    assert {why for _, why in report.ignored} == {"dead: built by their query initialiser, never called"}
    model.load_state_dict(sd, strict=True)
    pairs = {k: ours for k, ours, _ in report.mapped}
    assert pairs["pts_middle_encoder.conv4.0.0.weight"] == "pts_middle_encoder.net.stages.3.downsample.0.weight"
    assert pairs["pts_middle_encoder.shared_conv.0.bias"] == "pts_middle_encoder.net.shared_conv.0.bias"
    assert pairs["img_neck.fpn_convs.3.conv.weight"] == "img_neck.fpn_convs.3.conv.weight"
    assert pairs["pts_bbox_head.task_heads.0.rot.0.1.running_var"] == "pts_bbox_head.net.heads.rot.0.1.running_var"
    own = model.state_dict()
    unchanged = [k for k in pairs if "heatmap.1." not in k and "query_proj.0.weight" not in k]
    assert all(torch.equal(own[pairs[k]], theirs[k]) for k in unchanged)
    # their heatmap classes (Pedestrian, Cyclist, Car) in the config's order (Car, Pedestrian, Cyclist)
    assert list(cfg.class_names) == ["Car", "Pedestrian", "Cyclist"]
    bias = theirs["pts_bbox_head.task_heads.0.heatmap.1.bias"]
    assert torch.equal(own["pts_bbox_head.net.heads.hm.1.bias"], bias[[2, 0, 1]])
    # the paper's config (OpenPCDet's VoxelNeXt tail, four FPN levels) is not theirs: refused, naming the switch
    paper = MODELS.build(Config.fromfile(str(CONFIGS / "mssf_voxelnext_vod.py")).model)
    with pytest.raises(MSSFError, match="authors_layout=True"):
        convert_authors_mssf_v(ckpt, paper, cfg.class_names)
    # the loaded model through mmdet3d's own test step, on a generated VoD frame
    from mmdet3d.structures import LiDARInstance3DBoxes
    from mmengine.runner import Runner
    from test_mmdet3d_train import small_cfg

    root = write_tree(tmp_path / "vod", train=1, val=1)
    loader = Runner.build_dataloader(small_cfg("mssf_voxelnext_vod_authors.py", root, tmp_path).val_dataloader)
    model.eval()
    with torch.no_grad():
        (out,) = model.test_step(next(iter(loader)))
    pred = out.pred_instances_3d
    assert isinstance(pred.bboxes_3d, LiDARInstance3DBoxes) and len(pred.scores_3d) == len(pred.labels_3d)
    assert model.pts_middle_encoder.net.shared_conv[0].bias is not None  # their biased shared_conv ran
