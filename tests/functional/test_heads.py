"""Tests of the semantic-head functions against naive loops and hand-written formulas."""

from __future__ import annotations

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.heads import points_in_boxes, sigmoid_focal_loss, voxel_foreground_labels
from mssf_blocks.testing import assert_close, gradcheck64

YAWS = [0.0, math.pi / 2, -math.pi / 2, math.pi, -math.pi, 0.7311, -2.2]


def naive_in_box(p, box, origin="center", margin=0.0, eps=1e-6):
    """One point, one box, python floats: rotate the offset into the box frame and compare."""
    x, y, z, dx, dy, dz, yaw = box
    if origin == "bottom":
        z = z + dz / 2
    ox, oy, oz = p[0] - x, p[1] - y, p[2] - z
    c, s = math.cos(yaw), math.sin(yaw)
    lx = c * ox + s * oy
    ly = -s * ox + c * oy
    return (
        abs(lx) <= dx / 2 + margin + eps
        and abs(ly) <= dy / 2 + margin + eps
        and abs(oz) <= dz / 2 + margin + eps
    )


def face_points(box, offsets=(0.0, 1e-3, -1e-3), origin="center"):
    """Points on, just outside and just inside each face (and on edges/corners) of a box."""
    x, y, z, dx, dy, dz, yaw = box
    if origin == "bottom":
        z = z + dz / 2
    c, s = math.cos(yaw), math.sin(yaw)
    pts = []
    for off in offsets:
        for sign in (-1, 1):
            for local in (
                (sign * (dx / 2 + off), 0.1 * dy, -0.2 * dz),
                (0.3 * dx, sign * (dy / 2 + off), 0.1 * dz),
                (-0.1 * dx, 0.2 * dy, sign * (dz / 2 + off)),
                (sign * (dx / 2 + off), sign * (dy / 2 + off), sign * (dz / 2 + off)),
            ):
                lx, ly, lz = local
                pts.append([x + c * lx - s * ly, y + s * lx + c * ly, z + lz])
    return pts


@pytest.mark.parametrize("origin", ["center", "bottom"])
def test_points_in_boxes_matches_naive_loop(origin):
    g = torch.Generator().manual_seed(0)
    boxes = []
    for i, yaw in enumerate(YAWS):
        centre = (torch.rand(3, generator=g, dtype=torch.float64) * 6 - 3).tolist()
        size = (torch.rand(3, generator=g, dtype=torch.float64) * 3 + 0.5).tolist()
        boxes.append(centre + size + [yaw])
    pts = (torch.rand(200, 3, generator=g, dtype=torch.float64) * 10 - 5).tolist()
    for box in boxes:
        pts += face_points(box, origin=origin)
    points = torch.tensor(pts, dtype=torch.float64)
    bx = torch.tensor(boxes, dtype=torch.float64)
    got = points_in_boxes(points, bx, origin=origin)
    expected = torch.tensor([[naive_in_box(p, b, origin) for b in boxes] for p in pts])
    assert got.shape == (len(pts), len(boxes))
    assert torch.equal(got, expected)
    # The scene must exercise both outcomes near faces.
    assert 0 < int(got.sum()) < got.numel()


def test_points_on_faces_are_inside_and_just_outside_are_outside():
    for yaw in YAWS:
        box = [1.0, -2.0, 0.5, 4.0, 2.0, 1.5, yaw]
        on = torch.tensor(face_points(box, offsets=(0.0, -1e-3)), dtype=torch.float64)
        out = torch.tensor(face_points(box, offsets=(1e-3,)), dtype=torch.float64)
        bx = torch.tensor([box], dtype=torch.float64)
        assert bool(points_in_boxes(on, bx).all()), yaw
        assert not bool(points_in_boxes(out, bx).any()), yaw
        # float32 points on faces too (eps absorbs rounding of the rotation).
        assert bool(points_in_boxes(on.float(), bx.float(), eps=1e-5).all()), yaw


def test_points_in_boxes_bottom_origin_shifts_by_half_height():
    box = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]])
    pts = torch.tensor([[0.0, 0.0, 1.9], [0.0, 0.0, -0.5], [0.0, 0.0, 2.1]])
    assert points_in_boxes(pts, box, origin="bottom").flatten().tolist() == [True, False, False]
    assert points_in_boxes(pts, box, origin="center").flatten().tolist() == [False, True, False]


def test_points_in_boxes_margin_and_extra_columns():
    box = torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0, 5.0, 5.0]])  # trailing velocity columns
    pts = torch.tensor([[1.05, 0.0, 0.0], [0.0, -1.15, 0.0]])
    assert points_in_boxes(pts, box).flatten().tolist() == [False, False]
    assert points_in_boxes(pts, box, margin=0.1).flatten().tolist() == [True, False]


def test_points_in_boxes_empty():
    assert points_in_boxes(torch.zeros(5, 3), torch.zeros(0, 7)).shape == (5, 0)
    assert points_in_boxes(torch.zeros(0, 3), torch.ones(2, 7)).shape == (0, 2)


@pytest.mark.parametrize(
    "points, boxes, kwargs, match",
    [
        (torch.zeros(3, 2), torch.zeros(1, 7), {}, "points"),
        (torch.zeros(3, 3, dtype=torch.long), torch.zeros(1, 7), {}, "points"),
        (torch.zeros(3, 3), torch.zeros(1, 6), {}, "boxes"),
        (torch.zeros(3, 3), torch.zeros(7), {}, "boxes"),
        (torch.zeros(3, 3), torch.tensor([[0.0, 0, 0, -1, 1, 1, 0]]), {}, "boxes"),
        (torch.zeros(3, 3), torch.tensor([[0.0, 0, float("nan"), 1, 1, 1, 0]]), {}, "boxes"),
        (torch.zeros(3, 3), torch.zeros(1, 7), {"origin": "top"}, "origin"),
        (torch.zeros(3, 3), torch.zeros(1, 7), {"margin": -0.1}, "margin"),
        ("pts", torch.zeros(1, 7), {}, "points"),
    ],
)
def test_points_in_boxes_bad_input(points, boxes, kwargs, match):
    with pytest.raises(MSSFError, match=match):
        points_in_boxes(points, boxes, **kwargs)


# -- foreground labels ------------------------------------------------------------------------------
def naive_labels(centroids, batch, gt_boxes, margin):
    labels, ignore = [], []
    for p, b in zip(centroids.tolist(), batch.tolist()):
        boxes = gt_boxes[b].tolist()
        fg = any(naive_in_box(p, box) for box in boxes)
        near = any(naive_in_box(p, box, margin=margin) for box in boxes)
        labels.append(1.0 if fg else 0.0)
        ignore.append(near and not fg)
    return torch.tensor(labels, dtype=torch.float64), torch.tensor(ignore)


def test_voxel_foreground_labels_matches_naive_loop():
    g = torch.Generator().manual_seed(1)
    gt = [
        torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.3], [5.0, 5.0, 0.0, 1.0, 1.0, 2.0, math.pi / 2]],
                     dtype=torch.float64),
        torch.zeros(0, 7, dtype=torch.float64),  # a sample without boxes
        torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, -math.pi]], dtype=torch.float64),
    ]
    pts, batch = [], []
    for b, boxes in enumerate(gt):
        rand = (torch.rand(150, 3, generator=g, dtype=torch.float64) * 8 - 2).tolist()
        pts += rand
        batch += [b] * len(rand)
        for box in boxes.tolist():
            extra = face_points(box, offsets=(0.0, 0.05, -0.05, 0.15, 0.099))
            pts += extra
            batch += [b] * len(extra)
    # Sample 1 also gets points where sample 0's and 2's boxes are: they must stay background.
    for box in gt[0].tolist() + gt[2].tolist():
        extra = face_points(box, offsets=(-0.05,))
        pts += extra
        batch += [1] * len(extra)
    centroids = torch.tensor(pts, dtype=torch.float64)
    bidx = torch.tensor(batch, dtype=torch.int32)
    perm = torch.randperm(len(pts), generator=g)  # rows need not be grouped by batch
    centroids, bidx = centroids[perm], bidx[perm]
    labels, ignore = voxel_foreground_labels(centroids, bidx, gt, margin=0.1)
    exp_labels, exp_ignore = naive_labels(centroids, bidx, gt, 0.1)
    assert labels.dtype == torch.float64 and ignore.dtype == torch.bool
    assert torch.equal(labels, exp_labels)
    assert torch.equal(ignore, exp_ignore)
    assert int(labels.sum()) > 0 and int(ignore.sum()) > 0
    assert not bool((ignore & (labels > 0)).any())
    assert float(labels[bidx == 1].sum()) == 0 and not bool(ignore[bidx == 1].any())


def test_voxel_foreground_labels_hand_example():
    gt = [torch.tensor([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]])]
    c = torch.tensor([[0.0, 0.0, 0.0], [1.05, 0.0, 0.0], [1.2, 0.0, 0.0], [0.0, 0.0, 0.99]])
    labels, ignore = voxel_foreground_labels(c, torch.zeros(4, dtype=torch.long), gt)
    assert labels.tolist() == [1.0, 0.0, 0.0, 1.0]
    assert ignore.tolist() == [False, True, False, False]
    labels, ignore = voxel_foreground_labels(c, torch.zeros(4, dtype=torch.long), gt, margin=0.0)
    assert ignore.tolist() == [False] * 4


def test_voxel_foreground_labels_empty():
    labels, ignore = voxel_foreground_labels(torch.zeros(0, 3), torch.zeros(0, dtype=torch.long),
                                             [torch.zeros(0, 7)])
    assert labels.shape == (0,) and ignore.shape == (0,)
    labels, ignore = voxel_foreground_labels(torch.ones(3, 3), torch.zeros(3, dtype=torch.long),
                                             [torch.zeros(0, 7)])
    assert labels.tolist() == [0.0] * 3 and ignore.tolist() == [False] * 3


@pytest.mark.parametrize(
    "centroids, batch, gt, kwargs, match",
    [
        (torch.zeros(2, 3), torch.zeros(3, dtype=torch.long), [torch.zeros(0, 7)], {}, "batch_index"),
        (torch.zeros(2, 3), torch.zeros(2), [torch.zeros(0, 7)], {}, "batch_index"),
        (torch.zeros(2, 3), torch.tensor([0, 1]), [torch.zeros(0, 7)], {}, "batch_index"),
        (torch.zeros(2, 3), torch.zeros(2, dtype=torch.long), torch.zeros(1, 0, 7), {}, "gt_boxes"),
        (torch.zeros(2, 3), torch.zeros(2, dtype=torch.long), [torch.zeros(1, 5)], {}, r"gt_boxes\[0\]"),
        (torch.zeros(2, 2), torch.zeros(2, dtype=torch.long), [torch.zeros(0, 7)], {}, "centroids"),
        (torch.zeros(2, 3), torch.zeros(2, dtype=torch.long), [torch.zeros(0, 7)], {"margin": -1}, "margin"),
    ],
)
def test_voxel_foreground_labels_bad_input(centroids, batch, gt, kwargs, match):
    with pytest.raises(MSSFError, match=match):
        voxel_foreground_labels(centroids, batch, gt, **kwargs)


# -- focal loss -------------------------------------------------------------------------------------
def naive_focal(logits, targets, ignore, alpha, gamma):
    """Python-float focal loss, written as in Lin et al.: -alpha_t (1 - p_t)^gamma log(p_t)."""
    total, pos = 0.0, 0.0
    for x, t, ig in zip(logits, targets, ignore):
        if ig:
            continue
        p = 1.0 / (1.0 + math.exp(-x))
        if t == 1:
            total += -alpha * (1 - p) ** gamma * math.log(p)
            pos += 1
        else:
            total += -(1 - alpha) * p ** gamma * math.log(1 - p)
    return total / max(pos, 1.0)


@pytest.mark.parametrize("alpha, gamma", [(0.25, 2.0), (0.5, 0.0), (0.9, 1.5)])
def test_focal_loss_matches_formula(alpha, gamma):
    g = torch.Generator().manual_seed(2)
    logits = torch.randn(40, generator=g, dtype=torch.float64) * 3
    targets = (torch.rand(40, generator=g) < 0.3).double()
    ignore = torch.rand(40, generator=g) < 0.2
    got = sigmoid_focal_loss(logits, targets, ignore, alpha=alpha, gamma=gamma)
    exp = naive_focal(logits.tolist(), targets.tolist(), ignore.tolist(), alpha, gamma)
    assert_close(got, torch.tensor(exp, dtype=torch.float64))
    # Without ignore mask, and float32.
    got = sigmoid_focal_loss(logits.float(), targets.float(), alpha=alpha, gamma=gamma)
    exp = naive_focal(logits.tolist(), targets.tolist(), [False] * 40, alpha, gamma)
    assert_close(got, torch.tensor(exp, dtype=torch.float32))


def test_focal_loss_no_positives_normalises_by_one_and_reductions():
    logits = torch.tensor([0.0, 1.0], dtype=torch.float64)
    targets = torch.zeros(2, dtype=torch.float64)
    exp = naive_focal([0.0, 1.0], [0, 0], [False, False], 0.25, 2.0)
    assert_close(sigmoid_focal_loss(logits, targets), torch.tensor(exp, dtype=torch.float64))
    assert_close(sigmoid_focal_loss(logits, targets, reduction="sum"), torch.tensor(exp, dtype=torch.float64))
    assert_close(sigmoid_focal_loss(logits, targets, reduction="mean"),
                 torch.tensor(exp / 2, dtype=torch.float64))
    per = sigmoid_focal_loss(logits, targets, ignore=torch.tensor([True, False]), reduction="none")
    assert per[0] == 0 and per[1] > 0


def test_focal_loss_extreme_logits_finite():
    logits = torch.tensor([-200.0, 200.0, 90.0], requires_grad=True)
    targets = torch.tensor([1.0, 0.0, 1.0])
    loss = sigmoid_focal_loss(logits, targets)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()
    # A hopeless prediction costs ~ alpha * |logit| (log p ~ logit for very negative logits).
    assert abs(float(loss.detach()) - (0.25 * 200 + 0.75 * 200) / 2) < 1e-3


def test_focal_loss_empty_and_gradcheck():
    x = torch.zeros(0, requires_grad=True)
    loss = sigmoid_focal_loss(x, torch.zeros(0))
    loss.backward()
    assert float(loss.detach()) == 0.0 and x.grad.shape == (0,)
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(7, generator=g, dtype=torch.float64)
    targets = torch.tensor([1.0, 0, 0, 1, 0, 1, 0], dtype=torch.float64)
    ignore = torch.tensor([False, False, True, False, False, False, True])
    assert gradcheck64(lambda x: sigmoid_focal_loss(x, targets, ignore), [logits])
    assert gradcheck64(lambda x: sigmoid_focal_loss(x, targets, gamma=1.5, reduction="none"), [logits])


@pytest.mark.parametrize(
    "logits, targets, kwargs, match",
    [
        (torch.zeros(3), torch.zeros(4), {}, "targets"),
        (torch.zeros(3), torch.tensor([0.0, 2.0, 0.0]), {}, "targets"),
        (torch.zeros(3, dtype=torch.long), torch.zeros(3), {}, "logits"),
        (torch.tensor([0.0, float("nan"), 0.0]), torch.zeros(3), {}, "logits"),
        (torch.zeros(3), torch.zeros(3), {"ignore": torch.zeros(3)}, "ignore"),
        (torch.zeros(3), torch.zeros(3), {"ignore": torch.zeros(2, dtype=torch.bool)}, "ignore"),
        (torch.zeros(3), torch.zeros(3), {"gamma": -1.0}, "gamma"),
        (torch.zeros(3), torch.zeros(3), {"alpha": 1.5}, "alpha"),
        (torch.zeros(3), torch.zeros(3), {"reduction": "avg"}, "reduction"),
    ],
)
def test_focal_loss_bad_input(logits, targets, kwargs, match):
    with pytest.raises(MSSFError, match=match):
        sigmoid_focal_loss(logits, targets, **kwargs)
