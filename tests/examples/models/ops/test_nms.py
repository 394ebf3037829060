"""Rotated BEV NMS against a naive greedy loop written here (using box_iou_bev pair by pair)."""

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.models.ops.iou import box_iou_bev
from mssf_examples.models.ops.nms import batched_nms_bev, nms_bev, nms_bev_reference


def naive_nms(boxes, scores, thr):
    """Greedy NMS: best score first, ties by lower index; suppress when IoU > thr with a kept box."""
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    kept = []
    for i in order:
        ok = True
        for j in kept:
            if float(box_iou_bev(boxes[i][None].double(), boxes[j][None].double())[0, 0]) > thr:
                ok = False
                break
        if ok:
            kept.append(i)
    return kept


def _cluttered(n, seed):
    gen = torch.Generator().manual_seed(seed)
    xy = torch.rand(n, 2, generator=gen, dtype=torch.float64) * 6  # dense: many overlaps
    z = torch.zeros(n, 1, dtype=torch.float64)
    size = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 + 1
    yaw = (torch.rand(n, 1, generator=gen, dtype=torch.float64) * 2 - 1) * math.pi
    boxes = torch.cat([xy, z, size, yaw], dim=1)
    scores = torch.round(torch.rand(n, generator=gen, dtype=torch.float64) * 5) / 5  # many exact ties
    return boxes, scores


def test_hand_worked_chain_and_tie():
    boxes = torch.tensor(
        [
            [0.0, 0.0, 0.0, 4.0, 2.0, 1.0, 0.0],  # A, best
            [0.5, 0.0, 0.0, 4.0, 2.0, 1.0, 0.2],  # B overlaps A strongly (rotated) -> suppressed
            [3.5, 0.0, 0.0, 4.0, 2.0, 1.0, 0.0],  # C overlaps B a bit, A only 1/15 -> kept
            [10.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.7],  # D, E identical with equal scores: lower index wins
            [10.0, 0.0, 0.0, 2.0, 2.0, 1.0, 0.7],
        ],
        dtype=torch.float64,
    )
    scores = torch.tensor([0.9, 0.8, 0.7, 0.5, 0.5], dtype=torch.float64)
    assert float(box_iou_bev(boxes[0:1], boxes[1:2])[0, 0]) > 0.5
    assert nms_bev(boxes, scores, 0.5).tolist() == [0, 2, 3]
    assert nms_bev_reference(boxes, scores, 0.5).tolist() == [0, 2, 3]
    # A-C: intersection 0.5 x 2 = 1, union 8 + 8 - 1 = 15 -> IoU 1/15 > 0.05, so C goes too.
    assert abs(float(box_iou_bev(boxes[0:1], boxes[2:3])[0, 0]) - 1 / 15) < 1e-9
    assert nms_bev(boxes, scores, 0.05).tolist() == [0, 3]


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("thr", [0.1, 0.5])
def test_matches_naive_loop_on_cluttered_rotated_boxes(seed, thr):
    boxes, scores = _cluttered(40, seed)
    expected = naive_nms(boxes, scores, thr)
    assert len(expected) < 40  # the case really suppresses something
    assert nms_bev(boxes, scores, thr).tolist() == expected
    assert nms_bev(boxes.float(), scores.float(), thr).tolist() == expected


def test_reference_matches_naive_loop():
    boxes, scores = _cluttered(25, 5)
    assert nms_bev_reference(boxes, scores, 0.3).tolist() == naive_nms(boxes, scores, 0.3)


def test_pre_max_size_keeps_only_the_best():
    boxes, scores = _cluttered(30, 3)
    order = sorted(range(30), key=lambda i: (-float(scores[i]), i))[:10]
    expected = [order[i] for i in naive_nms(boxes[order], scores[order], 0.3)]
    assert nms_bev(boxes, scores, 0.3, pre_max_size=10).tolist() == expected


def test_batched_is_per_class():
    boxes, scores = _cluttered(40, 4)
    labels = torch.arange(40) % 3
    expected = []
    for c in range(3):
        idx = torch.nonzero(labels == c).flatten().tolist()
        expected += [idx[i] for i in naive_nms(boxes[idx], scores[idx], 0.3)]
    expected.sort(key=lambda i: (-float(scores[i]), i))
    assert batched_nms_bev(boxes, scores, labels, 0.3).tolist() == expected


def test_empty_and_bad_input():
    assert nms_bev(torch.zeros(0, 7), torch.zeros(0), 0.5).numel() == 0
    assert batched_nms_bev(torch.zeros(0, 7), torch.zeros(0), torch.zeros(0, dtype=torch.long), 0.5).numel() == 0
    with pytest.raises(MSSFError, match="scores"):
        nms_bev(torch.zeros(3, 7), torch.zeros(4), 0.5)
    with pytest.raises(MSSFError, match="iou_threshold"):
        nms_bev(torch.zeros(3, 7), torch.zeros(3), 1.5)
