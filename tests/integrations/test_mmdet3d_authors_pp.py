"""The MSSF authors' released MSSF-PP checkpoint in the real mmdet3d 1.4: ``mssf_pointpillars_vod_authors.py``.

Their tensor names and shapes are the list written out from their config and source in
tests/examples/models/test_authors_checkpoint.py (``their_mssf_pp_shapes``: ``VoxelNetFuse`` of
``pointpillars_hv_secfpn_8xb6-160e_vod-3d-3class_mm_bb_bevfeat_lr0001``, mmdet's ResNet-50 and FPN, mmdet3d's
``Anchor3DHead``); no download. Random tensors under those names:

* convert into the mmdet3d model built from the config (``MSSFPillarEncoder(layout="authors")``) with every tensor
  of theirs mapped but their two dead ``voxel_fuse.img_transform`` modules, nothing of ours missing, and load
  with ``strict=True``; the image branch and the 2D blocks carry their values unchanged;
* their head, built by mmdet3d from their ``bbox_head`` dict in their class order (Pedestrian, Cyclist, Car), and
  the converted head in the config's order predict the same scores and boxes, class for class (mmdet3d's
  ``Anchor3DHead`` on both sides);
* docs/frameworks.md's ``convert-authors`` line writes a checkpoint that its ``test`` line evaluates on a generated
  View-of-Delft tree (the authors' layout runs inside mmdet3d's runner, the VoD metric comes back).
"""

from __future__ import annotations

import importlib.util
import math
import shlex
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import CONFIGS, require_mmdet3d, write_tree  # noqa: E402
from test_mmdet3d_authors_anchor_head import HEAD_CFG, OURS, THEIRS  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
CONFIG = "mssf_pointpillars_vod_authors.py"
DEAD = ("middle_encoder.voxel_fuse.img_transform.", "backbone.voxel_fuse.img_transform.")


def _their_shapes():
    path = Path(__file__).resolve().parents[1] / "examples" / "models" / "test_authors_checkpoint.py"
    spec = importlib.util.spec_from_file_location("_their_mssf_pp_keys", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.their_mssf_pp_shapes()


def their_checkpoint(seed=0):
    """Random tensors under their names (BN variances positive, so that the model can run on them)."""
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for k, shape in _their_shapes().items():
        if shape == ():
            sd[k] = torch.tensor(5)
        elif k.endswith("running_var"):
            sd[k] = torch.rand(shape, generator=g) + 0.5
        else:
            sd[k] = 0.05 * torch.randn(shape, generator=g)
    return {"meta": {}, "state_dict": sd}


@pytest.fixture(scope="module")
def model():
    require_mmdet3d()
    from mmdet3d.registry import MODELS
    from mmengine.registry import init_default_scope

    from mssf_examples.mmdet3d.cli import load_config

    cfg = load_config(str(CONFIGS / CONFIG))
    init_default_scope("mmdet3d")
    assert cfg.model.pts_middle_encoder.layout == "authors" and cfg.model.img_neck.num_outs == 5
    return MODELS.build(cfg.model)


def test_their_checkpoint_loads_strictly(model):
    from mssf_examples.mmdet3d.authors_checkpoint import convert_authors_mmdet3d

    theirs = their_checkpoint()["state_dict"]
    state, report = convert_authors_mmdet3d(theirs, model, OURS)
    assert report.missing == []
    assert sorted(k for k, _ in report.ignored) == sorted(k for k in theirs if k.startswith(DEAD))
    assert len(report.ignored) == 14  # Linear + BN of each stage's query initialiser
    assert len(report.mapped) + len(report.ignored) == len(theirs)
    model.load_state_dict(state, strict=True)
    sd = model.state_dict()
    for k in ("img_backbone.layer3.2.conv2.weight", "img_neck.fpn_convs.3.conv.weight"):
        assert torch.equal(sd[k], theirs[k])
    assert torch.equal(sd["pts_middle_encoder.net.blocks.1.3.weight"], theirs["backbone.blocks.1.3.weight"])
    assert torch.equal(sd["pts_middle_encoder.net.deblocks.2.0.weight"], theirs["neck.deblocks.2.0.weight"])


def test_converted_head_predicts_as_theirs(model):
    from mmdet3d.registry import MODELS

    from mssf_examples.mmdet3d.authors_checkpoint import convert_authors_mmdet3d

    theirs_head = MODELS.build(dict(HEAD_CFG)).double().eval()
    ckpt = their_checkpoint()["state_dict"]
    g = torch.Generator().manual_seed(1)
    for k, v in theirs_head.state_dict().items():
        ckpt[f"bbox_head.{k}"] = torch.randn(v.shape, generator=g, dtype=torch.float64)
    theirs_head.load_state_dict({k[len("bbox_head."):]: v for k, v in ckpt.items() if k.startswith("bbox_head.")})
    state, _ = convert_authors_mmdet3d(ckpt, model, OURS)
    ours_head = model.pts_bbox_head.double().eval()
    prefix = "pts_bbox_head."
    ours_head.load_state_dict({k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)})
    ny, nx, rot = 6, 5, 2
    x = torch.randn(1, 384, ny, nx, generator=g, dtype=torch.float64)
    with torch.no_grad():
        (tc, tr, td), (oc, orr, od) = theirs_head.forward_single(x), ours_head.forward_single(x)
        t_anchors = theirs_head.prior_generator.grid_anchors([(ny, nx)], device="cpu")[0].reshape(ny * nx, 3, rot, 7)
        o_anchors = ours_head.prior_generator.grid_anchors([(ny, nx)], device="cpu")[0].reshape(ny * nx, 3, rot, 7)
    model.pts_bbox_head.float()

    def cells(t, per):  # (1, A * per, H, W) -> (H * W, classes, rot, per), mmdet3d's flattening
        return t.permute(0, 2, 3, 1).reshape(ny * nx, 3, rot, per)

    perm = [THEIRS.index(c) for c in OURS]
    close = lambda a, b: torch.testing.assert_close(a, b, rtol=0, atol=1e-12)  # noqa: E731
    for k in range(3):
        tk = perm[k]
        assert torch.equal(o_anchors[:, k], t_anchors[:, tk])  # the same anchors, listed in the config's order
        # (float64; the convolutions may sum in another order once the output channels are reordered)
        close(cells(oc, 3)[:, k], cells(tc, 3)[:, tk][..., perm])  # our class c is their perm[c]
        close(cells(orr, 7)[:, k], cells(tr, 7)[:, tk])
        close(cells(od, 2)[:, k], cells(td, 2)[:, tk])


def test_docs_lines_convert_then_test_in_mmdet3d(tmp_path, monkeypatch, capsys):
    """docs/frameworks.md's two lines (``RUN_AUTHORS``) in a folder laid out as the page assumes
    (``checkpoints/mssf_pp_authors.pth`` their key list with random values, ``data/view_of_delft`` a generated
    tree); ``test`` with ``--image-scale 160 100`` appended."""
    require_mmdet3d()
    from mssf_examples.mmdet3d.cli import main
    from test_mmdet3d_docs import REPO, RUN_AUTHORS

    write_tree(tmp_path / "data" / "view_of_delft", train=1, val=1)
    (tmp_path / "examples").symlink_to(REPO / "examples")
    (tmp_path / "checkpoints").mkdir()
    torch.save(their_checkpoint(), tmp_path / "checkpoints" / "mssf_pp_authors.pth")
    monkeypatch.chdir(tmp_path)
    convert, evaluate = RUN_AUTHORS
    assert main(shlex.split(convert)[3:]) == 0
    printed = capsys.readouterr().out
    n = len(_their_shapes())
    report = (f"mapped {n - 14}, ignored 14, missing 0\n"
              "  ignored 14: dead: built by their query initialiser, never called\n")
    assert report in printed
    assert f"```text\n{report}```" in (REPO / "docs" / "frameworks.md").read_text()  # the report the page prints
    assert main(shlex.split(evaluate)[3:] + ["--image-scale", "160", "100"]) == 0
    logs = "".join(p.read_text() for p in (tmp_path / "work_dirs" / "mssf_pointpillars_vod_authors").glob("*/*.log"))
    value = float(logs.split("VoD/entire_area/mAP/AP3D_R40: ")[1].split()[0])
    assert math.isfinite(value)


def test_authors_layout_and_converter_refuse_what_is_not_theirs():
    require_mmdet3d()
    from torch import nn

    from mssf_blocks.errors import MSSFError
    from mssf_blocks.integrations.mmdet3d_pillars import MSSFPillarEncoder
    from mssf_examples.mmdet3d.authors_checkpoint import convert_authors_mmdet3d

    grid = dict(in_channels=7, point_cloud_range=[0, -25.6, -3, 51.2, 25.6, 2], voxel_size=[0.16, 0.16, 5])
    with pytest.raises(MSSFError, match="layout: expected 'paper' or 'authors', got 'theirs'"):
        MSSFPillarEncoder(**grid, layout="theirs")
    with pytest.raises(MSSFError, match="layout: 'authors' is their MSSF-PP .* num_fusion_blocks=0"):
        MSSFPillarEncoder(**grid, layout="authors", num_fusion_blocks=0, image_channels=[256] * 5)
    paper = nn.Module()
    paper.pts_middle_encoder = MSSFPillarEncoder(**grid, num_fusion_blocks=0, seg_hidden=None)
    paper.pts_bbox_head = nn.Linear(1, 1)
    with pytest.raises(MSSFError, match=r"model: expected an MSSFDetector with .*layout='authors'"):
        convert_authors_mmdet3d(their_checkpoint()["state_dict"], paper)
