"""Smoke + determinism test of examples/train_demo.py (``--quick``: 3 steps, 4 + 4 scenes)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

pytest.importorskip("spconv")
pytest.importorskip("matplotlib")

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "examples"))

import train_demo  # noqa: E402

CLASSES = ("Car", "Pedestrian", "Cyclist")
KEYS = ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    ckpt = out / "ckpt.pt"
    assert train_demo.main(["--quick", "--lighting", "--out", str(out), "--save-checkpoint", str(ckpt)]) == 0
    return out, ckpt, json.loads((out / "metrics.json").read_text())


def test_metrics_have_both_models_and_table_keys(quick_run):
    out, _, m = quick_run
    assert set(m["results"]) == set(train_demo.MODELS)
    for res in m["results"].values():
        assert set(res) == {"entire_area", "driving_corridor"}
        for region in res.values():
            assert set(region) == set(CLASSES) | {"mAP"}
            for key in KEYS:
                v = region["mAP"][key]
                assert v is None or 0.0 <= v <= 100.0
    for name in train_demo.MODELS:
        assert name in m["table"]
        assert m["lighting"][name]
    assert m["models"] == {train_demo.MODELS[0]: 1, train_demo.MODELS[1]: 0}
    assert m["config"]["steps"] == 3
    pre = m["image_pretrain"]
    assert pre["steps"] == 3 and pre["val_pixel"]["classes"] == ["background", *CLASSES]
    assert len(pre["val_pixel"]["iou"]) == 4 and all(0.0 <= v <= 1.0 for v in pre["val_pixel"]["iou"])
    # curves start at the class shares of the 2D-foreground voxels, which add up to 1
    c = m["blur_curves"]
    counts = c["counts"]
    assert counts["fore2d"] == counts["fore3d"] + counts["blurred"] > 0
    assert c["tau"][0] == 0.0
    assert math.isclose(c["blur_ratio"][0], counts["blurred"] / counts["fore2d"], rel_tol=1e-12)
    assert math.isclose(c["foreground_recall"][0], counts["fore3d"] / counts["fore2d"], rel_tol=1e-12)


def test_pngs_written(quick_run):
    out, _, m = quick_run
    for name in m["figures"].values():
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 1000


def test_loaded_checkpoint_gives_identical_metrics(quick_run, tmp_path):
    """Evaluation is deterministic: the saved weights reproduce the run's metrics exactly."""
    _, ckpt, m = quick_run
    assert train_demo.main(["--quick", "--out", str(tmp_path), "--load-checkpoint", str(ckpt)]) == 0
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert again["results"] == m["results"]
    assert again["timings"]["models"][train_demo.MODELS[0]]["train_seconds"] == 0.0


def test_rerun_same_seed_identical(quick_run, tmp_path):
    """Training is deterministic too: a second run with the same seed gives the same losses and metrics."""
    _, _, m = quick_run
    assert train_demo.main(["--quick", "--lighting", "--out", str(tmp_path)]) == 0
    again = json.loads((tmp_path / "metrics.json").read_text())
    assert again["final_train_loss"] == m["final_train_loss"]
    assert again["results"] == m["results"]


def test_end_to_end_image_branch(tmp_path):
    """--image-branch end-to-end trains the image branch with the detector (no pre-training, no cache)."""
    assert train_demo.main(["--quick", "--image-branch", "end-to-end", "--out", str(tmp_path)]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["image_pretrain"] is None and "image_semantics" not in m["figures"]
    assert set(m["results"]) == set(train_demo.MODELS)


def test_bad_arguments():
    with pytest.raises(SystemExit):
        train_demo.parse_args(["--steps", "0"])
    with pytest.raises(SystemExit):
        train_demo.parse_args(["--train-scenes", "2", "--batch-size", "4"])
    with pytest.raises(SystemExit):
        train_demo.parse_args(["--image-pretrain-steps", "0"])
