"""Independent references shared by the KITTI-format tests (``test_kitti_io.py``, ``test_kitti_boxes.py``,
``test_kitti_layouts.py``): calibration text split by hand, box corners and their 2D boxes in plain float64
numpy, and the sensor <-> camera box round-trip check against a numpy inverse.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from mssf_examples.data.kitti_io import Calibration, camera_boxes_to_sensor, sensor_boxes_to_camera

VOD_HW = (1216, 1936)


def hand_calib(path: Path):
    """P2 (3x4), R0 (4x4 padded), Tr (4x4) from plain string splitting."""
    entries = {}
    for line in Path(path).read_text().splitlines():
        if ":" not in line:
            continue
        key, vals = line.split(":", 1)
        vals = vals.split()
        if vals:
            entries[key.strip()] = np.array([float(v) for v in vals], dtype=np.float64)
    p2 = entries["P2"].reshape(3, 4)
    r0 = np.eye(4)
    if "R0_rect" in entries:
        r0[:3, :3] = entries["R0_rect"].reshape(3, 3)
    tr = np.eye(4)
    tr[:3, :] = entries["Tr_velo_to_cam"].reshape(3, 4)
    return p2, r0, tr


def np_camera_corners(loc, hwl, ry):
    """KITTI corners in the camera frame: x = +-l/2, z = +-w/2, y in {0, -h}, rotated about Y."""
    h, w, l = hwl
    xs = np.array([l, l, -l, -l, l, l, -l, -l]) / 2
    ys = np.array([0, 0, 0, 0, -h, -h, -h, -h])
    zs = np.array([w, -w, -w, w, w, -w, -w, w]) / 2
    rot = np.array([[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]])
    return (rot @ np.stack([xs, ys, zs])).T + np.asarray(loc)


def np_box2d(corners, proj, hw):
    """Project ``(8, 3)`` corners with a 3x4 matrix, enclosing box clipped to [0, W-1] x [0, H-1]."""
    hom = np.concatenate([corners, np.ones((8, 1))], axis=1) @ proj.T
    u, v = hom[:, 0] / hom[:, 2], hom[:, 1] / hom[:, 2]
    h, w = hw
    return np.array([np.clip(u.min(), 0, w - 1), np.clip(v.min(), 0, h - 1),
                     np.clip(u.max(), 0, w - 1), np.clip(v.max(), 0, h - 1)])


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def rot_xyz(rx, ry, rz):
    cx, sx, cy, sy, cz, sz = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry), math.cos(rz), math.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mz @ my @ mx


#: sensor (x forward, y left, z up) -> camera (x right, y down, z forward)
PERM = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def make_calib(p2, r0_3x3, tr_3x4) -> Calibration:
    t = lambda a: torch.tensor(np.asarray(a), dtype=torch.float64)  # noqa: E731
    return Calibration(P2=t(p2), R0_rect=t(r0_3x3), Tr_velo_to_cam=t(tr_3x4))


def random_sensor_boxes(n, seed):
    g = np.random.default_rng(seed)
    xyz = g.uniform([2, -20, -2], [50, 20, 1], size=(n, 3))
    dims = g.uniform(0.3, 5.0, size=(n, 3))
    yaw = g.uniform(-math.pi, math.pi, size=(n, 1))
    return torch.tensor(np.concatenate([xyz, dims, yaw], axis=1), dtype=torch.float64)


def check_round_trips(calib: Calibration, seed: int) -> None:
    boxes = random_sensor_boxes(200, seed)
    loc, hwl, ry = sensor_boxes_to_camera(boxes, calib)
    back = camera_boxes_to_sensor(loc, hwl, ry, calib)
    np.testing.assert_allclose(back[:, :6].numpy(), boxes[:, :6].numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(wrap(back[:, 6].numpy() - boxes[:, 6].numpy()), 0, atol=1e-9)

    g = np.random.default_rng(seed + 1)
    loc = torch.tensor(g.uniform([-20, -1, 2], [20, 2, 50], size=(200, 3)))
    hwl = torch.tensor(g.uniform(0.3, 5.0, size=(200, 3)))
    ry = torch.tensor(g.uniform(-math.pi, math.pi, size=200))
    boxes = camera_boxes_to_sensor(loc, hwl, ry, calib)
    loc2, hwl2, ry2 = sensor_boxes_to_camera(boxes, calib)
    np.testing.assert_allclose(loc2.numpy(), loc.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(hwl2.numpy(), hwl.numpy(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(wrap(ry2.numpy() - ry.numpy()), 0, atol=1e-9)

    # independent forward reference: the heading from two points mapped with the numpy inverse
    s2c = np.eye(4)
    s2c[:3, :3] = calib.R0_rect.numpy()
    tr = np.eye(4)
    tr[:3] = calib.Tr_velo_to_cam.numpy()
    c2s = np.linalg.inv(s2c @ tr)
    for i in range(0, 200, 17):
        h, w, l = hwl[i].tolist()
        bottom = loc[i].numpy()
        centre = bottom - np.array([0, h / 2, 0])
        front = centre + l / 2 * np.array([math.cos(ry[i]), 0, -math.sin(ry[i])])
        cs, fs = (c2s @ np.append(centre, 1))[:3], (c2s @ np.append(front, 1))[:3]
        np.testing.assert_allclose(boxes[i, :3].numpy(), cs, rtol=0, atol=1e-9)
        assert abs(wrap(float(boxes[i, 6]) - math.atan2(fs[1] - cs[1], fs[0] - cs[0]))) < 1e-9
        np.testing.assert_allclose(boxes[i, 3:6].numpy(), [l, w, h], rtol=0, atol=0)
