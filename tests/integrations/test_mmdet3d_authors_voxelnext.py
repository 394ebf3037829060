"""The MSSF authors' MSSF-V checkpoint (``EricLiuhhh/MSSF``, mmdet3d) into the mmdet3d MSSF-V built as theirs
(``mssf_voxelnext_vod_authors.py``): their key list, written out from their configs
(``vx_mm_r50_ablation_n2m4`` on ``voxelnext_voxel005_vod_multimodal_r50pytorch``: tests/examples/models/
test_authors_checkpoint.py's ``their_mssf_v_shapes``; no download), filled with seeded values, converts with every
tensor mapped or ignored for a reason and nothing missing, and loads with ``strict=True``; the values land where the
name rules say (their heatmap classes permuted to the config's order), and mmdet3d's ``test_step`` runs the loaded
model on a generated VoD frame (the authors' encoder, five FPN levels, their head) to ``LiDARInstance3DBoxes``.

The encoder's two spellings of "built as the authors'": ``layout="authors"`` (the config's, the word of
``MSSFPillarEncoder`` too) and the older ``layout="VoxelResBackBone8xVoxelNeXt", authors_layout=True`` build the same
module (state-dict keys, outputs on the same weights and batch); a contradiction between them is refused, named."""

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
    assert cfg.model.pts_middle_encoder.layout == "authors" and "authors_layout" not in cfg.model.pts_middle_encoder
    init_default_scope("mmdet3d")
    model = MODELS.build(cfg.model)
    assert model.pts_middle_encoder.layout == "authors" and model.pts_middle_encoder.authors_layout
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
    with pytest.raises(MSSFError, match="layout='authors'.*got pts_middle_encoder=MSSFSparseEncoder, "
                                        "layout='VoxelResBackBone8xVoxelNeXt'"):
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


# the encoder on its own, at test widths, with fusion (their two MSDFF blocks and the semantic head) on the batch that
# test_mmdet3d_plugin builds as mmdet3d does (voxelization, metainfo, two 8-channel image levels)
_GRID = dict(sparse_shape=[41, 64, 64], point_cloud_range=[0, -25.6, -3, 51.2, 25.6, 2], voxel_size=[0.8, 0.8, 0.125])
_SMALL = dict(num_fusion_blocks=2, image_channels=[8, 8], msdff_heads=2, msdff_points=2, seg_hidden=[16],
              channels=[8, 8, 8, 16, 16, 16, 16], out_channels=16)


def _encoder(seed, **layout):
    pytest.importorskip("spconv")
    from mssf_blocks.integrations.mmdet3d_plugin import MSSFSparseEncoder

    torch.manual_seed(seed)
    return MSSFSparseEncoder(7, **_GRID, **_SMALL, **layout)


def test_layout_authors_and_authors_layout_build_the_same_encoder():
    from test_mmdet3d_plugin import make_batch

    new = _encoder(0, layout="authors")
    old = _encoder(1, layout="VoxelResBackBone8xVoxelNeXt", authors_layout=True)
    both = _encoder(2, layout="authors", authors_layout=True)  # redundant, not contradictory
    paper = _encoder(3, layout="VoxelResBackBone8xVoxelNeXt")  # OpenPCDet's tail: another module
    assert list(new.state_dict()) == list(old.state_dict()) == list(both.state_dict())
    assert list(new.state_dict()) != list(paper.state_dict())  # (the key comparison can tell layouts apart)
    assert "net.shared_conv.0.bias" in new.state_dict() and "net.shared_conv.0.bias" not in paper.state_dict()
    for enc in (new, old, both):
        assert enc.layout == "authors" and enc.authors_layout is True and enc.net.authors_layout
        assert enc.sparse_bev and enc.sparse_shape == [41, 64, 64]
    assert paper.layout == "VoxelResBackBone8xVoxelNeXt" and paper.authors_layout is False
    # the same weights, the same batch: the same sparse BEV, bit for bit (built from other seeds, so equality is
    # the weights' doing, not the seeds')
    weights_differ = any(not torch.equal(a, b) for a, b in zip(new.state_dict().values(), old.state_dict().values())
                       if a.is_floating_point() and a.numel() > 1)
    assert weights_differ
    old.load_state_dict(new.state_dict(), strict=True)
    voxel_features, coors, points, img_feats, metas = make_batch()
    img_feats = [f.detach() for f in img_feats]
    outs = []
    for enc in (new, old):
        enc.eval()
        with torch.no_grad():
            (bev,) = enc(voxel_features, coors, 2, points=points, img_features=img_feats, batch_input_metas=metas)
        outs.append(bev)
    a, b = outs
    assert a.features.shape[0] > 0 and a.features.shape[1] == 16 and list(a.spatial_shape) == [8, 8]
    assert torch.equal(a.indices, b.indices) and torch.equal(a.features, b.features)
    assert a.features.abs().sum() > 0


@pytest.mark.parametrize("layout,authors_layout,match", [
    ("VoxelBackBone8x", True, "authors_layout: True means layout='authors'.*got layout='VoxelBackBone8x'"),
    ("VoxelResBackBone8x", True, "authors_layout: True means layout='authors'.*got layout='VoxelResBackBone8x'"),
    ("authors", False, "authors_layout: expected True or unset with layout='authors'.*got False"),
    ("Authors", None, r"layout: expected one of \[.*'authors'\], got 'Authors'"),
])
def test_contradicting_spellings_are_refused_by_name(layout, authors_layout, match):
    from mssf_blocks.errors import MSSFError
    from mssf_blocks.integrations.mmdet3d_plugin import MSSFSparseEncoder

    with pytest.raises(MSSFError, match=match):
        MSSFSparseEncoder(7, **_GRID, **_SMALL, layout=layout, authors_layout=authors_layout)
