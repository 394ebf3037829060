"""The training CLI applies the dataset recipe's augmentation (docs/training.md), on a tiny VoD-layout tree."""

from __future__ import annotations

import json
import math

import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.data.kitti_export import write_vod_tree  # noqa: E402
from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset  # noqa: E402

SIZE = (64, 104)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    cfg = SceneConfig(image_size=SIZE)
    train = [SyntheticDataset("train", 4, cfg, seed=4)[i] for i in range(4)]
    root = tmp_path_factory.mktemp("vod_aug")
    write_vod_tree(root, {"train": train})
    return root


def _args(root, out, *extra):
    return ["train", "--dataset", "vod", "--data-root", str(root), "--preset", "tiny", "--steps", "2",
            "--batch-size", "2", "--threads", "1", "--no-progress", "--out", str(out), *extra]


def _capture(monkeypatch, steps=2):
    """Replace train_detector by one that records the batches it is given."""
    seen = []

    def fake(model, batches, steps, lr, **kw):
        it = iter(batches)
        seen.extend(next(it) for _ in range(steps))
        seen.append(lr)
        return dict(seconds=0.0, seconds_per_step=0.0, history=[{"loss": 0.0}])

    monkeypatch.setattr(cli, "train_detector", fake)
    return seen


def test_recipe_defaults_reach_the_training_batches(root, tmp_path, monkeypatch):
    seen = _capture(monkeypatch)
    assert cli.main(_args(root, tmp_path)) == 0
    *batches, lr = seen
    assert lr == pytest.approx(5e-3)  # VoD, n = 2: the authors' initial 5e-4, one-cycle peak 10 x
    cfg = json.loads((tmp_path / "config.json").read_text())
    assert cfg["lr"] == pytest.approx(5e-3) and cfg["recipe"] == "vod"
    aug = cfg["augmentation"]
    assert aug["flip_prob"] == 0.5 and aug["sync_image_flip"] is True
    assert aug["rotation_range"] == pytest.approx([-math.pi / 4, math.pi / 4]) and aug["scale_range"] == [0.95, 1.05]
    for b in batches:
        assert b.points_to_sensor is not None and b.points_to_sensor.shape == (2, 4, 4)
        # a rotation/scale was drawn per sample: not the identity
        assert (b.points_to_sensor - torch.eye(4)).abs().amax(dim=(1, 2)).min() > 1e-4


def test_no_augment_and_options(root, tmp_path, monkeypatch):
    seen = _capture(monkeypatch)
    assert cli.main(_args(root, tmp_path / "a", "--no-augment", "--fusion-blocks", "1")) == 0
    assert all(b.points_to_sensor is None for b in seen[:-1]) and seen[-1] == pytest.approx(1e-2)
    seen.clear()
    assert cli.main(_args(root, tmp_path / "b", "--flip-prob", "1", "--no-sync-image-flip", "--rotation-range", "0",
                          "0", "--scale-range", "1", "1", "--lr", "1e-3")) == 0
    for b in seen[:-1]:  # y -> -y flip only, the image left alone
        torch.testing.assert_close(b.points_to_sensor, torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0])).expand(2, 4, 4))
    assert seen[-1] == 1e-3
    cfg = json.loads((tmp_path / "b" / "config.json").read_text())
    assert cfg["augmentation"]["sync_image_flip"] is False and cfg["augmentation"]["flip_prob"] == 1.0


def test_bad_augmentation_option_is_an_argparse_error(root, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(_args(root, tmp_path, "--flip-prob", "1.5"))
    assert e.value.code == 2
    assert "flip_prob" in capsys.readouterr().err


# Training with the default (augmented) recipe end to end, twice with the same seed: test_cli.py's
# test_train_is_deterministic (its runs use the defaults, so they are augmented).
