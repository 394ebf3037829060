"""The demo's image-branch pre-training: targets, caching, and that it learns."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.models.image_branch import ImageBranch
from mssf_examples.training.image_pretrain import (
    collate_with_features, precompute_features, pretrain_image_branch, segmentation_metrics, semantic_map)
from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset


@pytest.fixture(scope="module")
def scenes():
    ds = SyntheticDataset("train", 6, SceneConfig(image_size=(64, 96)), seed=3)
    return [ds[i] for i in range(len(ds))]


def test_semantic_map_hand_built():
    # 2 objects (labels 2 and 0), then clutter items 2 and 3, background -1
    inst = torch.tensor([[-1, 0, 1], [2, 3, 1]])
    scene = SimpleNamespace(instance_map=inst, gt_labels=torch.tensor([2, 0]))
    assert semantic_map(scene).tolist() == [[0, 3, 1], [0, 0, 1]]
    with pytest.raises(MSSFError, match="gt_labels"):
        semantic_map(SimpleNamespace(instance_map=inst, gt_labels=torch.tensor([5, 0])))


def test_semantic_map_matches_scene_loop(scenes):
    s = scenes[0]
    m = semantic_map(s)
    g = s.gt_labels.numel()
    for y in range(0, 64, 5):
        for x in range(0, 96, 7):
            i = int(s.instance_map[y, x])
            expect = int(s.gt_labels[i]) + 1 if 0 <= i < g else 0
            assert int(m[y, x]) == expect


def test_precomputed_features_equal_branch_and_collate(scenes):
    torch.manual_seed(0)
    branch = ImageBranch(18, 4, 8, 4).eval()
    feats = precompute_features(branch, scenes[:3], batch_size=2)
    with torch.no_grad():
        direct = branch(torch.stack([s.image for s in scenes[:3]])[:, None])
    for b in range(3):
        for level, f in enumerate(feats[b]):
            torch.testing.assert_close(f, direct[level][b], rtol=1e-5, atol=1e-6)
    batch = collate_with_features(scenes[1:3], feats[1:3])
    assert batch.images is None and batch.image_size == scenes[0].image_size
    assert [tuple(f.shape[:2]) for f in batch.image_features] == [(2, 1)] * 4
    torch.testing.assert_close(batch.image_features[2][0, 0], direct[2][1, 0], rtol=1e-5, atol=1e-6)
    with pytest.raises(MSSFError, match="features"):
        collate_with_features(scenes[:2], feats[:1])


def test_pretraining_learns_and_is_deterministic(scenes):
    def run():
        torch.manual_seed(0)
        branch = ImageBranch(18, 4, 8, 4)
        log = pretrain_image_branch(branch, scenes, steps=30, batch_size=3, lr=1e-2, seed=1)
        return branch, log

    torch.set_num_threads(1)
    branch, log = run()
    h = log["history"]
    assert sum(h[-5:]) / 5 < 0.6 * sum(h[:5]) / 5
    metrics = segmentation_metrics(branch, log["readout"], scenes)
    assert metrics["iou"][0] > 0.8  # background is learnt in any case
    assert max(metrics["recall"][1:]) > 0.2  # and at least one object class starts to appear
    _, again = run()
    assert again["history"] == h


def test_bad_arguments(scenes):
    branch = ImageBranch(18, 4, 8, 4)
    with pytest.raises(MSSFError, match="steps"):
        pretrain_image_branch(branch, scenes, steps=0)
    with pytest.raises(MSSFError, match="batch_size"):
        pretrain_image_branch(branch, scenes, steps=1, batch_size=7)
    with pytest.raises(MSSFError, match="frozen"):
        pretrain_image_branch(ImageBranch(18, 4, 8, 4, frozen=True), scenes, steps=1, batch_size=2)
