"""Target assignment on hand-built cases with hand-computed answers."""

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.models.heads.common import BEVGrid
from mssf_examples.models.ops.targets import (
    assign_anchor_targets,
    axis_aligned_iou,
    center_targets,
    gaussian_radius,
    nearest_bev_boxes,
    sparse_center_targets,
)


def _box(x, y, dx, dy, yaw=0.0, z=0.0, dz=1.0):
    return [x, y, z, dx, dy, dz, yaw]


def test_nearest_bev_rounds_yaw_to_right_angles():
    boxes = torch.tensor([_box(0, 0, 4, 2, yaw) for yaw in (0.3, 1.2, -1.2, math.pi - 0.1)])
    expected = torch.tensor([[-2, -1, 2, 1], [-1, -2, 1, 2], [-1, -2, 1, 2], [-2, -1, 2, 1]], dtype=torch.float32)
    torch.testing.assert_close(nearest_bev_boxes(boxes), expected)


def test_axis_aligned_iou_hand_worked():
    a = torch.tensor([[0.0, 0.0, 2.0, 2.0]])
    b = torch.tensor([[1.0, 1.0, 3.0, 3.0], [5.0, 5.0, 6.0, 6.0], [0.0, 0.0, 2.0, 2.0]])
    torch.testing.assert_close(axis_aligned_iou(a, b), torch.tensor([[1 / 7, 0.0, 1.0]]))


def test_anchor_assignment_hand_built():
    # One 4 x 2 m class-0 box at the origin (yaw 0.1 rounds to 0), one small class-0 box far away, one
    # class-1 box overlapping no anchor. Anchors and their nearest-BEV IoU with box 0 (worked by hand):
    anchors = torch.tensor(
        [
            _box(0.0, 0, 4, 2),  # 0: IoU 1                        -> positive
            _box(1.0, 0, 4, 2),  # 1: inter 3*2=6, union 10 = 0.6  -> positive (>= 0.6)
            _box(1.5, 0, 4, 2),  # 2: inter 2.5*2=5, union 11 = 0.4545 -> ignored (0.45 <= IoU < 0.6)
            _box(10.0, 0, 4, 2),  # 3: IoU 0                        -> background
            _box(0.0, 0, 4, 2, math.pi / 2),  # 4: 2x4 vs 4x2: inter 4, union 12 = 1/3 -> background
            _box(20.5, 0, 4, 2),  # 5: vs box 1 (1x1 at x=20): inter 1, union 8 = 0.125, its best -> forced
            _box(0.0, 0, 4, 2),  # 6: class-1 anchor on box 0: other class never matches -> background
        ],
        dtype=torch.float64,
    )
    anchor_classes = torch.tensor([0, 0, 0, 0, 0, 0, 1])
    gt = torch.tensor([_box(0, 0, 4, 2, 0.1), _box(20, 0, 1, 1), _box(50, 50, 4, 2)], dtype=torch.float64)
    labels = torch.tensor([0, 0, 1])
    t = assign_anchor_targets(anchors, anchor_classes, gt, labels, [0.6, 0.5], [0.45, 0.35], num_classes=2)
    assert t.labels.tolist() == [1, 1, -1, 0, 0, 1, 0]
    assert t.matched_gt.tolist() == [0, 0, -1, -1, -1, 1, -1]
    # Raising class 0's matched threshold turns anchor 1 into ignored; anchor 0 stays (also forced).
    t = assign_anchor_targets(anchors, anchor_classes, gt, labels, 0.7, 0.45, num_classes=2)
    assert t.labels.tolist() == [1, -1, -1, 0, 0, 1, 0]


def test_anchor_assignment_without_ground_truth():
    anchors = torch.tensor([_box(0, 0, 4, 2), _box(3, 0, 4, 2)])
    no_boxes, no_labels = torch.zeros(0, 7), torch.zeros(0, dtype=torch.long)
    t = assign_anchor_targets(anchors, torch.tensor([0, 1]), no_boxes, no_labels, 0.6, 0.45, 2)
    assert t.labels.tolist() == [0, 0]
    assert t.matched_gt.tolist() == [-1, -1]
    with pytest.raises(MSSFError, match="matched_thresholds"):
        assign_anchor_targets(anchors, torch.tensor([0, 1]), no_boxes, no_labels, [0.6], 0.45, 2)
    # the same GT checks as the centre heads: labels in range, positive sizes (log-encoded)
    with pytest.raises(MSSFError, match="gt_labels"):
        assign_anchor_targets(anchors, torch.tensor([0, 1]), torch.ones(1, 7), torch.tensor([2]), 0.6, 0.45, 2)
    with pytest.raises(MSSFError, match="sizes"):
        assign_anchor_targets(anchors, torch.tensor([0, 1]), torch.zeros(1, 7), torch.tensor([0]), 0.6, 0.45, 2)


def test_gaussian_radius_hand_worked():
    # 4 x 2 cells, overlap 0.1: r1 = (6 + sqrt(36 - 4 * 7.2 / 1.1)) / 2, r2 = (12 + sqrt(144 - 115.2)) / 2,
    # r3 = (-1.2 + sqrt(1.44 + 11.52)) / 2 = 1.2 is the smallest.
    r = gaussian_radius(torch.tensor([4.0], dtype=torch.float64), torch.tensor([2.0], dtype=torch.float64), 0.1)
    assert abs(float(r) - 1.2) < 1e-12
    # 20 x 12 cells: r3 = (-6.4 + sqrt(40.96 + 345.6)) / 2 = 6.6305...
    r = gaussian_radius(torch.tensor([20.0], dtype=torch.float64), torch.tensor([12.0], dtype=torch.float64), 0.1)
    assert abs(float(r) - (-6.4 + math.sqrt(386.56)) / 2) < 1e-12


GRID = BEVGrid(0.0, -4.0, 8.0, 4.0, 16, 16)  # 0.5 m cells


def test_center_heatmap_peak_and_radius_hand_worked():
    # Centre (3.3, 0.2) -> u = 6.6, v = 8.4 -> cell (col 6, row 8). Size 2 x 1 m = 4 x 2 cells -> radius
    # int(1.2) = 1 -> raised to min_radius 2 -> sigma = 5/6, 1 / (2 sigma^2) = 0.72.
    gt = torch.tensor([[3.3, 0.2, 0.5, 2.0, 1.0, 1.5, 0.3]], dtype=torch.float64)
    t = center_targets(gt, torch.tensor([1]), GRID, num_classes=2)
    hm = t.heatmap
    assert hm.shape == (2, 16, 16)
    assert float(hm[0].abs().sum()) == 0.0
    assert float(hm[1, 8, 6]) == 1.0 and float(hm[1].max()) == 1.0
    assert abs(float(hm[1, 8, 7]) - math.exp(-0.72)) < 1e-12
    assert abs(float(hm[1, 10, 8]) - math.exp(-8 * 0.72)) < 1e-12
    assert abs(float(hm[1, 6, 5]) - math.exp(-5 * 0.72)) < 1e-12
    assert int((hm[1] > 0).sum()) == 25  # the 5 x 5 window of radius 2 and nothing else
    assert float(hm[1, 8, 9]) == 0.0 and float(hm[1, 11, 6]) == 0.0
    assert t.cell_index.tolist() == [[6, 8]] and t.radius.tolist() == [2]
    expected = [0.6, 0.4, 0.5, math.log(2.0), 0.0, math.log(1.5), math.sin(0.3), math.cos(0.3)]
    torch.testing.assert_close(t.regression, torch.tensor([expected], dtype=torch.float64), rtol=0, atol=1e-12)
    # Without the minimum the radius is int(1.2) = 1: a 3 x 3 window.
    t = center_targets(gt, torch.tensor([1]), GRID, num_classes=2, min_radius=0)
    assert t.radius.tolist() == [1] and int((t.heatmap[1] > 0).sum()) == 9


def test_center_heatmap_border_overlap_and_outside():
    gt = torch.tensor(
        [
            [0.1, -3.9, 0.0, 2.0, 1.0, 1.0, 0.0],  # cell (0, 0): radius-2 window clipped to 3 x 3
            [1.1, -3.9, 0.0, 2.0, 1.0, 1.0, 0.0],  # cell (2, 0): overlaps, max-combined
            [9.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0],  # outside the grid: no target
        ],
        dtype=torch.float64,
    )
    t = center_targets(gt, torch.tensor([0, 0, 0]), GRID, num_classes=1)
    assert t.gt_index.tolist() == [0, 1]
    hm = t.heatmap[0]
    assert float(hm[0, 0]) == 1.0 and float(hm[0, 2]) == 1.0
    assert abs(float(hm[0, 1]) - math.exp(-0.72)) < 1e-12  # both give exp(-0.72) there
    assert abs(float(hm[1, 1]) - math.exp(-2 * 0.72)) < 1e-12
    assert int((hm > 0).sum()) == 3 * 5  # columns 0..4, rows 0..2
    empty = center_targets(torch.zeros(0, 7), torch.zeros(0, dtype=torch.long), GRID, 1)
    assert float(empty.heatmap.sum()) == 0.0 and empty.regression.shape == (0, 8)


def test_sparse_targets_nearest_voxel_and_dense_values():
    # Centre cell (6, 8), (u, v) = (6.6, 8.4).
    gt = torch.tensor([[3.3, 0.2, 0.5, 2.0, 1.0, 1.5, 0.3]], dtype=torch.float64)
    # Voxels (col, row); the centre cell itself is empty. Cell centres' distances to (6.6, 8.4):
    # (7, 8): (0.9, 0.1) -> 0.82; (6, 9): (0.1, 1.1) -> 1.22; (4, 8): far; (15, 15): outside the window.
    # Heatmap = max(dense Gaussian around cell (6, 8), same Gaussian around the assigned voxel (7, 8)),
    # both radius 2 (window |d| <= 2), exponent -0.72 * squared cell offset:
    # (4, 8): max(offset (-2, 0), outside) = exp(-4 * 0.72); (6, 9): max((0, 1), (-1, 1)) = exp(-0.72);
    # (8, 9): max((2, 1), (1, 1)) = exp(-2 * 0.72); (9, 8): max(outside, (2, 0)) = exp(-4 * 0.72).
    cells = torch.tensor([[4, 8], [7, 8], [6, 9], [15, 15], [8, 9], [9, 8]])
    t = sparse_center_targets(gt, torch.tensor([0]), cells, GRID, num_classes=1)
    assert t.voxel_index.tolist() == [1]
    e = math.exp
    expected = torch.tensor([e(-4 * 0.72), 1.0, e(-0.72), 0.0, e(-2 * 0.72), e(-4 * 0.72)], dtype=torch.float64)
    torch.testing.assert_close(t.heatmap[:, 0], expected, rtol=0, atol=1e-12)
    # Regression is relative to the assigned voxel's index: offsets (6.6 - 7, 8.4 - 8).
    torch.testing.assert_close(t.regression[0, :2], torch.tensor([-0.4, 0.4], dtype=torch.float64), rtol=0, atol=1e-12)
    none = sparse_center_targets(gt, torch.tensor([0]), torch.zeros(0, 2, dtype=torch.long), GRID, 1)
    assert none.heatmap.shape == (0, 1) and none.voxel_index.numel() == 0


def test_sparse_targets_equal_dense_when_the_centre_cell_is_occupied():
    gt = torch.tensor([[3.3, 0.2, 0.5, 2.0, 1.0, 1.5, 0.3], [6.1, -2.2, 0.0, 3.0, 1.5, 1.5, 1.0]], dtype=torch.float64)
    labels = torch.tensor([0, 1])
    gen = torch.Generator().manual_seed(0)
    flat = torch.randperm(256, generator=gen)[:80]
    cells = torch.stack([flat % 16, flat // 16], 1)
    cells = torch.unique(torch.cat([cells, torch.tensor([[6, 8], [12, 3]])]), dim=0)  # both centre cells
    dense = center_targets(gt, labels, GRID, num_classes=2).heatmap
    t = sparse_center_targets(gt, labels, cells, GRID, num_classes=2)
    torch.testing.assert_close(t.heatmap, dense[:, cells[:, 1], cells[:, 0]].T, rtol=0, atol=0)
    assert cells[t.voxel_index].tolist() == [[6, 8], [12, 3]]


def test_bad_labels_raise():
    with pytest.raises(MSSFError, match="gt_labels"):
        center_targets(torch.ones(1, 7), torch.tensor([3]), GRID, num_classes=2)
    with pytest.raises(MSSFError, match="sizes"):
        center_targets(torch.zeros(1, 7), torch.tensor([0]), GRID, num_classes=2)
