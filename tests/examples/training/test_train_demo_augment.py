"""examples/train_demo.py --augmentation compare: the fusion model with and without augmentation, same budget."""

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


def test_compare_trains_a_third_model_with_augmentation(tmp_path):
    assert train_demo.main(["--quick", "--augmentation", "compare", "--threads", "1", "--out", str(tmp_path)]) == 0
    m = json.loads((tmp_path / "metrics.json").read_text())
    names = (*train_demo.MODELS, train_demo.AUGMENTED_MODEL)
    assert set(m["results"]) == set(names)
    aug = m["augmentation"]
    assert aug["mode"] == "compare" and aug["augmented_models"] == [train_demo.AUGMENTED_MODEL]
    assert aug["config"]["flip_prob"] == 0.5 and aug["config"]["sync_image_flip"] is True
    assert set(aug["augmented_minus_plain_mAP_AP3D_R11"]) == {"entire_area", "driving_corridor"}
    # same budget: as many steps for both fusion models, same seed; the data differ (augmented)
    plain, augd = m["final_train_loss"][train_demo.MODELS[0]], m["final_train_loss"][train_demo.AUGMENTED_MODEL]
    assert math.isfinite(augd["loss"]) and plain["loss"] != augd["loss"]
    t = m["timings"]["models"]
    assert "seconds_per_step" in t[train_demo.AUGMENTED_MODEL]


def test_augmentation_option_values():
    assert train_demo.parse_args(["--quick"]).augmentation == "off"
    with pytest.raises(SystemExit):
        train_demo.parse_args(["--augmentation", "maybe"])
