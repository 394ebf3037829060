"""Tests for the sensor <-> camera box conversions of ``mssf_examples.data.kitti_io`` (``sensor_boxes_to_camera``,
``camera_boxes_to_sensor``, ``sensor_box_corners``).

References are independent of the code under test: round trips under synthetic, axis-permutation and real
calibrations checked against a numpy inverse, hand-worked boxes, 2D boxes of the label corners in plain
float64 numpy. The real-calibration tests skip when ``../shared/realdata`` is absent.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.data.kitti_io import (
    Calibration,
    camera_boxes_to_sensor,
    parse_labels,
    project_boxes_2d,
    read_calibration,
    sensor_box_corners,
    sensor_boxes_to_camera,
)

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from kitti_references import (  # noqa: E402
    PERM, VOD_HW, check_round_trips, hand_calib, make_calib, np_box2d, np_camera_corners, random_sensor_boxes, rot_xyz,
    wrap)


def synthetic_rotated_calib() -> Calibration:
    p2 = np.array([[700.0, 0, 600, 45.0], [0, 710.0, 180, -0.3], [0, 0, 1, 0.005]])
    r0 = rot_xyz(0.01, -0.008, 0.012)
    tr = np.concatenate([PERM @ rot_xyz(0.3, 0.25, 0.2), [[0.1], [-1.2], [0.4]]], axis=1)
    return make_calib(p2, r0, tr)


def real_calibs(realdata_root: Path):
    return {
        "vod_00549": read_calibration(realdata_root / "vod/radar/calib/00549.txt"),
        "vod_01047": read_calibration(realdata_root / "vod/radar/calib/01047.txt"),
        "kitti": read_calibration(realdata_root / "kitti/calib/000000.txt"),
    }


# ---------------------------------------------------------------------------------------------------
# box conversion round trips
# ---------------------------------------------------------------------------------------------------
def test_round_trip_synthetic_rotated_calib():
    calib = synthetic_rotated_calib()
    assert abs(float(calib.sensor_to_camera[1, 2]) + 1) > 0.05  # the tilt is real
    check_round_trips(calib, seed=0)


def test_round_trip_permutation_calib_matches_shortcut():
    calib = make_calib(np.eye(3, 4), np.eye(3), np.concatenate([PERM, [[0.0], [0.0], [0.0]]], axis=1))
    check_round_trips(calib, seed=3)
    loc = torch.tensor([[1.0, 1.5, 10.0]])
    boxes = camera_boxes_to_sensor(loc, torch.tensor([[1.5, 0.6, 2.0]]), torch.tensor([0.3]), calib)
    # hand-worked: sensor x = cam z = 10, y = -cam x = -1, z = -(cam y - h/2) = -(1.5 - 0.75) = -0.75
    np.testing.assert_allclose(boxes.numpy(), [[10.0, -1.0, -0.75, 2.0, 0.6, 1.5, -0.3 - math.pi / 2]], atol=1e-12)


@pytest.mark.realdata
def test_round_trip_real_calibs(realdata_root):
    if not (realdata_root / "vod").is_dir() or not (realdata_root / "kitti").is_dir():
        pytest.skip(f"vod/ or kitti/ missing under {realdata_root}")
    for k, (name, calib) in enumerate(real_calibs(realdata_root).items()):
        check_round_trips(calib, seed=10 + k)


def test_degenerate_calib_is_rejected():
    # sensor z axis maps to camera x: no camera-Y component, yaw cannot be converted
    rot = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    calib = make_calib(np.eye(3, 4), np.eye(3), np.concatenate([rot, np.zeros((3, 1))], axis=1))
    with pytest.raises(MSSFError, match="camera Y"):
        sensor_boxes_to_camera(random_sensor_boxes(2, 0), calib)


# ---------------------------------------------------------------------------------------------------
# a real VoD label file under an axis-permutation extrinsic
# ---------------------------------------------------------------------------------------------------
@pytest.mark.realdata
def test_upright_sensor_boxes_exact_without_tilt(realdata_root):
    """With an axis-permutation extrinsic the 7-number sensor boxes reproduce the 2D boxes exactly.

    (With VoD's tilted radar extrinsics they cannot: an upright sensor box is not the camera-upright
    label box; see the mssf_examples.data.kitti_boxes module docstring and docs/real-data.md for the measured deviation.)
    """
    path = realdata_root / "vod/label_2/01047.txt"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    p2, _, tr = hand_calib(realdata_root / "vod/radar/calib/01047.txt")
    tr_perm = np.concatenate([PERM, tr[:3, 3:]], axis=1)
    calib = make_calib(p2, np.eye(3), tr_perm)
    objects = parse_labels(path.read_text())
    boxes = camera_boxes_to_sensor(objects.location, objects.dimensions, objects.rotation_y, calib)
    # hand formula valid for a pure permutation: yaw = -ry - pi/2, z_centre = z_bottom + h/2
    np.testing.assert_allclose(wrap(boxes[:, 6].numpy() - (-objects.rotation_y.numpy() - math.pi / 2)), 0, atol=1e-12)
    got, _ = project_boxes_2d(sensor_box_corners(boxes), calib.lidar2img, VOD_HW)
    lidar2img = p2 @ np.concatenate([tr_perm, [[0, 0, 0, 1]]])
    for i in range(len(objects)):
        ref = np_box2d(np_camera_corners(objects.location[i].numpy(), objects.dimensions[i].numpy(),
                                         float(objects.rotation_y[i])), p2, VOD_HW)
        np.testing.assert_allclose(got[i].numpy(), ref, rtol=0, atol=1e-8)
        # and the corners themselves, through the independent numpy matrix
        np.testing.assert_allclose(np_box2d(sensor_box_corners(boxes)[i].numpy(), lidar2img, VOD_HW), ref,
                                   rtol=0, atol=1e-8)
