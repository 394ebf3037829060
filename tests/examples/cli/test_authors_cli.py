"""An authors' whole checkpoint through the command line: ``convert-authors`` -> ``eval``.

Fabricated checkpoints of their MSSF-PP and MSSF-V (their key lists and shapes, written out in
``test_authors_checkpoint.py``; random tensors, BN variances positive) are converted into the example
detectors built as theirs (``MSSFDetector(..., layout="authors")``), must fill every tensor and load with
``strict=True``; the written checkpoint is then evaluated on the generated VoD tree (``generated_tree.py``)
by ``eval --checkpoint``, which prints the VoD table.
"""

import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
sys.path.insert(0, str(Path(__file__).parents[1] / "models"))
from generated_tree import write_generated_tree  # noqa: E402
from test_authors_checkpoint import their_mssf_pp_shapes, their_mssf_v_shapes  # noqa: E402

from mssf_examples.cli.commands import main  # noqa: E402
from mssf_examples.models.detectors import build_detector  # noqa: E402
from mssf_examples.training.loop import load_checkpoint  # noqa: E402


def plausible_checkpoint(shapes, seed):
    """Random tensors under their names: small weights, unit BN scales, positive variances."""
    g = torch.Generator().manual_seed(seed)
    sd = {}
    for k, v in shapes.items():
        if v == ():
            sd[k] = torch.tensor(9)
        elif k.endswith("running_var"):
            sd[k] = 1 + torch.rand(v, generator=g)
        elif k.endswith("running_mean") or k.endswith("bias"):
            sd[k] = 0.01 * torch.randn(v, generator=g)
        elif len(v) == 1:  # BN / LayerNorm scales
            sd[k] = torch.ones(v)
        else:
            fan_in = 1
            for n in v[1:]:
                fan_in *= n
            sd[k] = torch.randn(v, generator=g) / fan_in**0.5
    return {"meta": {"mmdet3d_version": "1.x"}, "state_dict": sd}


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_generated_tree(tmp_path_factory.mktemp("vod_authors"))


@pytest.mark.parametrize("layout", ["mssf_pp", "mssf_v"])
def test_converted_authors_checkpoint_evaluates_through_the_cli(layout, tree, tmp_path, capsys):
    root, ids, _ = tree
    shapes = their_mssf_pp_shapes() if layout == "mssf_pp" else their_mssf_v_shapes()
    src, out = tmp_path / f"{layout}.pth", tmp_path / f"{layout}_examples.pt"
    theirs = plausible_checkpoint(shapes, seed=11)
    torch.save(theirs, src)
    assert main(["convert-authors", str(src), "--out", str(out), "--layout", layout]) == 0
    text = capsys.readouterr().out
    state, config = load_checkpoint(out)
    report = torch.load(out, weights_only=True)["report"]
    ignored = report["ignored"]
    # every tensor of theirs mapped or ignored; the ignored ones: the query initialisers' dead img_transform
    assert len(report["mapped"]) + len(ignored) == len(shapes) and report["missing"] == []
    assert ignored and all(".voxel_fuse.img_transform." in k for k, _ in ignored)
    assert f"mapped {len(report['mapped'])}, ignored {len(ignored)}, missing 0" in text and "strict=True" in text
    assert config["layout"] == "authors" and config["detector"] == ("pointpillars" if layout == "mssf_pp" else "voxelnext")
    from mssf_examples.cli.loading import _preset_from_json

    model = build_detector(config["detector"], _preset_from_json(config["preset"]), config["fusion_blocks"],
                           config["fusion"], layout="authors")
    model.load_state_dict(state, strict=True)
    head = "bbox_head.conv_reg.weight" if layout == "mssf_pp" else "pts_bbox_head.task_heads.0.dim.0.0.weight"
    mine = "head.conv_box.weight" if layout == "mssf_pp" else "head.heads.dim.0.0.weight"
    got, want = state[mine], theirs["state_dict"][head]
    assert sorted(got.flatten().tolist()) == sorted(want.flatten().tolist())  # the same values (permuted rows)

    with pytest.raises(SystemExit):  # the converted checkpoint names no data root
        main(["eval", "--checkpoint", str(out)])
    assert "--data-root: required" in capsys.readouterr().err
    ev = tmp_path / "eval"
    assert main(["eval", "--checkpoint", str(out), "--data-root", str(root), "--split", "val", "--threads", "1",
                 "--no-progress", "--out", str(ev)]) == 0
    printed = capsys.readouterr().out
    assert "Entire annotated area" in printed and "Driving corridor" in printed
    assert sorted(p.stem for p in (ev / "predictions").glob("*.txt")) == ids["val"]


def test_convert_authors_names_an_unknown_tensor_and_a_missing_one(tmp_path, capsys):
    src, out = tmp_path / "bad.pth", tmp_path / "x.pt"
    sd = plausible_checkpoint(their_mssf_pp_shapes(), 1)["state_dict"]
    torch.save({"state_dict": {**sd, "pts_voxel_layer.x": torch.zeros(1)}}, src)
    with pytest.raises(SystemExit):
        main(["convert-authors", str(src), "--out", str(out)])
    assert "pts_voxel_layer.x" in capsys.readouterr().err and not out.exists()
    torch.save({"state_dict": {k: v for k, v in sd.items() if k != "bbox_head.conv_cls.bias"}}, src)
    assert main(["convert-authors", str(src), "--out", str(out)]) == 1
    assert "missing: head.conv_cls.bias" in capsys.readouterr().out and not out.exists()
