"""``image_boxes_2d``: image extent of camera-frame boxes, cut at the near plane and clipped."""

from __future__ import annotations

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.data.kitti_export import image_boxes_2d
from mssf_examples.data.kitti_io import camera_box_corners, project_boxes_2d

F64 = dict(dtype=torch.float64)
P2 = torch.tensor([[1000.0, 0, 960, 0], [0, 1000.0, 600, 0], [0, 0, 1.0, 0]], **F64)
SIZE = (1216, 1936)


def corners(loc, hwl, ry):
    return camera_box_corners(torch.tensor([loc], **F64), torch.tensor([hwl], **F64), torch.tensor([ry], **F64))


def test_box_reaching_behind_the_camera_is_clipped_not_zeroed():
    # Length 4 m along camera z (ry = -pi/2), from z = -1 to 3 m, x in [1, 3], y in [-0.5, 0.5]. The part
    # in front starts at the near plane, where it projects far right / above / below the image: the
    # box runs to the right, top and bottom borders. Its left edge is the nearest in-front corner
    # column at x = 1, z = 3: u = 960 + 1000 / 3. The old projection wrote 0 0 0 0 (a corner behind).
    c = corners((2.0, 0.5, 1.0), (1.0, 2.0, 4.0), -math.pi / 2)
    box = image_boxes_2d(c, P2, SIZE)[0]
    assert box.tolist() == pytest.approx([960 + 1000 / 3, 0.0, 1935.0, 1215.0])
    identity = torch.eye(4, **F64)[:3]
    old, in_front = project_boxes_2d(c, P2 @ torch.cat([identity, torch.tensor([[0, 0, 0, 1.0]], **F64)]), SIZE)
    assert not bool(in_front[0]) and old[0].tolist() == [0, 0, 0, 0]


def test_box_in_front_equals_corner_projection_and_behind_is_empty():
    c = corners((1.0, 1.5, 12.0), (1.5, 1.8, 4.0), 0.4)
    four = torch.cat([torch.eye(3, 4, **F64), torch.tensor([[0, 0, 0, 1.0]], **F64)])
    old, _ = project_boxes_2d(c, P2 @ four, SIZE)
    assert torch.allclose(image_boxes_2d(c, P2, SIZE), old)
    behind = corners((0.0, 1.5, -10.0), (1.5, 1.8, 4.0), 0.0)
    assert image_boxes_2d(behind, P2, SIZE).tolist() == [[0.0, 0.0, 0.0, 0.0]]


def test_bad_input():
    with pytest.raises(MSSFError, match="corners"):
        image_boxes_2d(torch.zeros(2, 4, 3), P2, SIZE)
    with pytest.raises(MSSFError, match="near"):
        image_boxes_2d(torch.zeros(1, 8, 3), P2, SIZE, near=0.0)


def test_kitti_lines_write_the_clipped_box_of_a_prediction_reaching_behind_the_camera():
    # Sensor frame = camera at the origin looking along +x (x_cam = -y, y_cam = -z, z_cam = x). A car
    # from x = -1 to 3 m, 2 m to the right: the line's 2D box reaches the right border (was 0 0 0 0).
    from mssf_examples.data.kitti_export import kitti_lines
    from mssf_examples.data.kitti_io import Calibration

    tr = torch.tensor([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [1.0, 0.0, 0.0, 0.0]], **F64)
    calib = Calibration(P2=P2, R0_rect=torch.eye(3, **F64), Tr_velo_to_cam=tr)
    boxes = torch.tensor([[1.0, -2.0, 0.0, 4.0, 2.0, 1.0, 0.0]], **F64)
    line = kitti_lines(boxes, torch.tensor([0]), ["Car"], calib, SIZE, scores=torch.tensor([0.5]))[0]
    left, top, right, bottom = (float(v) for v in line.split()[4:8])
    assert left == pytest.approx(960 + 1000 * 1 / 3) and (top, right, bottom) == (0.0, 1935.0, 1215.0)
