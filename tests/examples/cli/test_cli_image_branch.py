"""Issue 42, item 2: ``train`` refuses a frozen image branch that loads no weights (it would train the
fusion on a random, frozen ResNet's features without a word), naming ``--image-weights`` and the two
ways out, as OpenPCDet's route does for ``MODEL.IMAGE_BRANCH``. Before the fix the paper preset's
default command (``--fusion-blocks 2``, frozen branch, no ``--image-weights``) trained silently.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.models.image_branch import ImageBranch  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from cli_refusal import refused_line as _fails  # noqa: E402
from generated_tree import write_generated_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


class _Built(Exception):
    """Raised in place of training: the detector was built and its options accepted."""


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_generated_tree(tmp_path_factory.mktemp("vod"))[0]


@pytest.fixture
def no_training(monkeypatch):
    def stop(model, *args, **kwargs):
        raise _Built(model)

    monkeypatch.setattr(cli, "train_detector", stop)


def _train(root, out, *extra):
    return ["train", "--dataset", "vod", "--data-root", str(root), "--steps", "1", "--batch-size", "2",
            "--threads", "1", "--no-progress", "--workers", "0", "--no-augment", "--out", str(out), *extra]




def test_paper_preset_frozen_branch_without_weights_is_refused(tree, tmp_path, capsys, no_training):
    line = _fails(_train(tree, tmp_path / "o", "--detector", "second", "--fusion-blocks", "1"), capsys)
    assert "--image-weights" in line and "frozen image branch needs pre-trained weights" in line
    assert "--train-image-branch" in line and "--preset paper" in line
    assert not (tmp_path / "o").exists()


def test_the_two_ways_out_and_radar_only_are_accepted(tree, tmp_path, no_training):
    with pytest.raises(_Built) as built:  # trained with the detector
        cli.main(_train(tree, tmp_path / "a", "--detector", "second", "--fusion-blocks", "1", "--train-image-branch"))
    assert not built.value.args[0].image_branch.frozen
    with pytest.raises(_Built) as built:  # radar only: no image branch at all
        cli.main(_train(tree, tmp_path / "b", "--detector", "second", "--fusion-blocks", "0"))
    assert built.value.args[0].image_branch is None


def test_a_frozen_branch_with_weights_loads_them(tree, tmp_path, capsys, monkeypatch, no_training):
    """The tiny preset made frozen: refused without weights, and with ``--image-weights`` the branch holds
    exactly the file's tensors (the check does not stand in the way of the documented route)."""
    tiny = cli.cli_tiny_preset
    monkeypatch.setattr(cli, "cli_tiny_preset", lambda *a, **k: dataclasses.replace(tiny(*a, **k),
                                                                                    freeze_image_branch=True))
    args = ("--preset", "tiny", "--detector", "second", "--fusion-blocks", "1")
    line = _fails(_train(tree, tmp_path / "o", *args), capsys)
    assert "--image-weights" in line and "--preset tiny freezes it" in line
    p = tiny(cli.DATASETS["vod"].preset, (64, 104))
    torch.manual_seed(5)
    branch = ImageBranch(p.image_depth, p.image_base_channels, p.fpn_channels, p.num_image_levels)
    torch.save(branch.state_dict(), tmp_path / "branch.pt")
    with pytest.raises(_Built) as built:
        cli.main(_train(tree, tmp_path / "o", *args, "--image-weights", str(tmp_path / "branch.pt")))
    got = built.value.args[0].image_branch
    assert got.frozen
    for k, v in branch.state_dict().items():
        assert torch.equal(got.state_dict()[k], v), k
