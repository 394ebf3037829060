"""KITTI camera-frame boxes <-> the library's sensor-frame boxes, box corners and their 2D projections.

Part of :mod:`mssf_examples.data.kitti_io` (which re-exports every public name).

Box conversion (exact, not the usual ``-ry - pi/2`` shortcut)
-------------------------------------------------------------
A KITTI label is a box that is upright in the *camera* frame: bottom-face centre ``loc``, size
``(h, w, l)``, heading ``d_cam = (cos ry, 0, -sin ry)`` (the direction of the length, rotated by
``ry`` about camera Y, which points down). Let ``T = R0_rect(4x4) @ Tr_velo_to_cam(4x4)`` map the sensor
frame to the camera frame and ``A`` be its 3 x 3 linear part.

* centre: camera centre ``loc - (0, h/2, 0)``, mapped with ``T^-1``;
* size: ``dx = l``, ``dy = w``, ``dz = h``;
* yaw: the heading in the sensor frame is ``A^-1 d_cam = (a, b, c)``; ``yaw = atan2(b, a)``.

When ``A`` is a pure axis permutation (camera x = -y_s, y = -z_s, z = x_s) this is ``yaw = -ry - pi/2``;
VoD's radar-to-camera extrinsics are rotated by a few degrees, where the shortcut is off by up to a few
tenths of a degree (and the ``+h/2`` along sensor z misplaces the centre by several centimetres).

The inverse maps a sensor yaw back to the unique camera heading with zero camera-y component whose
sensor-frame projection onto the ground plane points along ``yaw``: with ``u = A (cos yaw, sin yaw, 0)``
and ``v = A e_z``, ``d = u - (u_y / v_y) v`` (then ``ry = atan2(-d_z, d_x)``). Both directions are exact
inverses (round trip to ~1e-15), defined whenever the sensor's z axis is not parallel to the camera's
image plane horizontal (``v_y != 0``).

A 7-number sensor box is upright in the *sensor* frame. With tilted extrinsics (VoD: ~6 deg) it is not
the same solid as the camera-upright label box: same centre, size and ground heading, but its corners
differ by ``~ h/2 * tilt``. :func:`camera_box_corners_in_sensor` gives the label's exact corners in the
sensor frame when they are needed (e.g. to reproduce the labelled 2D boxes).
"""

from __future__ import annotations

from typing import Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.geometry import project_points

from .kitti_calib import Calibration
from .kitti_labels import KittiObjects

__all__ = [
    "transform_points",
    "camera_boxes_to_sensor",
    "sensor_boxes_to_camera",
    "camera_box_corners",
    "sensor_box_corners",
    "camera_box_corners_in_sensor",
    "project_boxes_2d",
    "points_in_image",
]


def transform_points(points: Tensor, matrix: Tensor) -> Tensor:
    """Apply a ``(4, 4)`` (or ``(3, 4)``) affine matrix to ``(..., 3)`` points (float64)."""
    m = matrix.to(torch.float64)
    p = points.to(torch.float64)
    return p @ m[:3, :3].T + m[:3, 3]


def _vertical_in_camera(calib: Calibration) -> Tensor:
    """``A e_z``: the sensor's up axis in the camera frame; its y entry must not vanish."""
    v = calib.sensor_to_camera[:3, 2]
    if abs(float(v[1])) < 1e-6 * float(v.norm()):
        raise MSSFError(
            "calib: expected the sensor z axis to have a component along camera Y (the camera's vertical), "
            f"got A e_z = {v.tolist()}; camera-Y boxes and sensor-z yaw cannot be converted"
        )
    return v


def camera_boxes_to_sensor(
    location: Tensor, dimensions: Tensor, rotation_y: Tensor, calib: Calibration
) -> Tensor:
    """KITTI camera-frame boxes -> ``(G, 7)`` float64 sensor boxes ``(x, y, z, dx, dy, dz, yaw)``.

    Args:
        location: ``(G, 3)`` bottom-face centre in the rectified camera frame.
        dimensions: ``(G, 3)`` ``(h, w, l)``.
        rotation_y: ``(G,)`` rotation about camera Y.
        calib: the frame's :class:`Calibration`.

    Returns:
        ``(G, 7)``: centre (z = box centre), ``dx = l``, ``dy = w``, ``dz = h``, and ``yaw`` the angle
        of the heading vector mapped to the sensor frame (exact; see the module docstring).
    """
    _vertical_in_camera(calib)
    loc = location.to(torch.float64).reshape(-1, 3)
    hwl = dimensions.to(torch.float64).reshape(-1, 3)
    ry = rotation_y.to(torch.float64).reshape(-1)
    if not (loc.shape[0] == hwl.shape[0] == ry.shape[0]):
        raise MSSFError(
            f"location, dimensions, rotation_y: expected G rows each, got {loc.shape[0]}, {hwl.shape[0]}, {ry.shape[0]}"
        )
    h, w, l = hwl.unbind(1)
    centre_cam = loc - torch.stack([torch.zeros_like(h), h / 2, torch.zeros_like(h)], dim=1)
    cam2sen = calib.camera_to_sensor
    centre = transform_points(centre_cam, cam2sen)
    heading_cam = torch.stack([torch.cos(ry), torch.zeros_like(ry), -torch.sin(ry)], dim=1)
    heading = heading_cam @ cam2sen[:3, :3].T
    yaw = torch.atan2(heading[:, 1], heading[:, 0])
    return torch.cat([centre, torch.stack([l, w, h, yaw], dim=1)], dim=1)


def sensor_boxes_to_camera(boxes: Tensor, calib: Calibration) -> Tuple[Tensor, Tensor, Tensor]:
    """Inverse of :func:`camera_boxes_to_sensor`.

    Args:
        boxes: ``(G, 7)`` sensor boxes ``(x, y, z, dx, dy, dz, yaw)``.
        calib: the frame's :class:`Calibration`.

    Returns:
        ``location (G, 3)`` (bottom-face centre, camera frame), ``dimensions (G, 3)`` ``(h, w, l)`` and
        ``rotation_y (G,)`` in ``(-pi, pi]``, all float64.
    """
    if boxes.dim() != 2 or boxes.shape[1] != 7:
        raise MSSFError(f"boxes: expected shape (G, 7), got {tuple(boxes.shape)}")
    v = _vertical_in_camera(calib)
    b = boxes.to(torch.float64)
    sen2cam = calib.sensor_to_camera
    centre_cam = transform_points(b[:, :3], sen2cam)
    l, w, h, yaw = b[:, 3], b[:, 4], b[:, 5], b[:, 6]
    loc = centre_cam + torch.stack([torch.zeros_like(h), h / 2, torch.zeros_like(h)], dim=1)
    ground = torch.stack([torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw)], dim=1)
    u = ground @ sen2cam[:3, :3].T
    # Move along the sensor's up axis until the camera-y component vanishes: the sensor-frame ground
    # projection of the result is still (cos yaw, sin yaw), so the forward conversion gives yaw back.
    d = u - (u[:, 1:2] / v[1]) * v
    ry = torch.atan2(-d[:, 2], d[:, 0])
    return loc, torch.stack([h, w, l], dim=1), ry


def camera_box_corners(location: Tensor, dimensions: Tensor, rotation_y: Tensor) -> Tensor:
    """``(G, 8, 3)`` corners of KITTI camera-frame boxes (bottom face first, then top).

    ``x = +-l/2``, ``z = +-w/2``, ``y`` from ``0`` to ``-h``, rotated by ``rotation_y`` about Y and moved
    to ``location``.
    """
    loc = location.to(torch.float64).reshape(-1, 3)
    h, w, l = dimensions.to(torch.float64).reshape(-1, 3).unbind(1)
    ry = rotation_y.to(torch.float64).reshape(-1)
    sx = torch.tensor([1, 1, -1, -1, 1, 1, -1, -1], dtype=torch.float64)
    sz = torch.tensor([1, -1, -1, 1, 1, -1, -1, 1], dtype=torch.float64)
    top = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1], dtype=torch.float64)
    x = sx * l[:, None] / 2
    z = sz * w[:, None] / 2
    y = -top * h[:, None]
    c, s = torch.cos(ry)[:, None], torch.sin(ry)[:, None]
    # R_y(ry) = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    xr = c * x + s * z
    zr = -s * x + c * z
    return torch.stack([xr, y, zr], dim=-1) + loc[:, None, :]


def sensor_box_corners(boxes: Tensor) -> Tensor:
    """``(G, 8, 3)`` corners of sensor boxes ``(x, y, z, dx, dy, dz, yaw)`` (bottom face first)."""
    if boxes.dim() != 2 or boxes.shape[1] < 7:
        raise MSSFError(f"boxes: expected shape (G, 7), got {tuple(boxes.shape)}")
    b = boxes.to(torch.float64)
    sx = torch.tensor([1, 1, -1, -1, 1, 1, -1, -1], dtype=torch.float64)
    sy = torch.tensor([1, -1, -1, 1, 1, -1, -1, 1], dtype=torch.float64)
    sz = torch.tensor([-1, -1, -1, -1, 1, 1, 1, 1], dtype=torch.float64)
    x = sx * b[:, 3:4] / 2
    y = sy * b[:, 4:5] / 2
    z = sz * b[:, 5:6] / 2
    c, s = torch.cos(b[:, 6:7]), torch.sin(b[:, 6:7])
    return torch.stack([c * x - s * y, s * x + c * y, z], dim=-1) + b[:, None, :3]


def camera_box_corners_in_sensor(objects: KittiObjects, calib: Calibration) -> Tensor:
    """``(G, 8, 3)`` exact corners of the (camera-upright) label boxes in the sensor frame."""
    corners = camera_box_corners(objects.location, objects.dimensions, objects.rotation_y)
    return transform_points(corners, calib.camera_to_sensor)


def project_boxes_2d(
    corners: Tensor, lidar2img: Tensor, image_size: Sequence[int], eps: float = 1e-5
) -> Tuple[Tensor, Tensor]:
    """Enclosing 2D boxes of projected corners, clipped to the image.

    Clipping follows KITTI/VoD: ``left, right`` to ``[0, W - 1]`` and ``top, bottom`` to ``[0, H - 1]``.

    Args:
        corners: ``(G, 8, 3)`` sensor-frame corners.
        lidar2img: ``(3, 4)``.
        image_size: ``(H, W)``.
        eps: corners with depth ``<= eps`` are behind the camera.

    Returns:
        ``boxes (G, 4)`` float64 ``(left, top, right, bottom)`` and ``in_front (G,)`` bool (all 8 corners
        in front of the camera); rows that are not in front are zeros.
    """
    if corners.dim() != 3 or tuple(corners.shape[1:]) != (8, 3):
        raise MSSFError(f"corners: expected shape (G, 8, 3), got {tuple(corners.shape)}")
    h, w = (int(s) for s in image_size)
    g = corners.shape[0]
    flat = corners.reshape(-1, 3).to(torch.float64)
    proj = project_points(flat, torch.zeros(flat.shape[0], dtype=torch.long),
                          lidar2img.to(torch.float64).reshape(1, 3, 4), (h, w), eps=eps)
    pix = proj.pixel[:, 0].reshape(g, 8, 2)
    in_front = (proj.depth[:, 0].reshape(g, 8) > eps).all(dim=1)
    lo, hi = pix.amin(dim=1), pix.amax(dim=1)
    boxes = torch.cat([lo, hi], dim=1)
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clamp(0, w - 1)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clamp(0, h - 1)
    boxes = torch.where(in_front[:, None], boxes, torch.zeros_like(boxes))
    return boxes, in_front


def points_in_image(points: Tensor, lidar2img: Tensor, image_size: Sequence[int], eps: float = 1e-5) -> Tensor:
    """``(P,)`` bool: depth ``> eps`` and the projected pixel within ``[-0.5, W - 0.5] x [-0.5, H - 0.5]``.

    This is the ``valid`` mask of the library's projector (normalised ``uv`` in ``[0, 1]``).
    """
    proj = project_points(points[:, :3].to(torch.float64), torch.zeros(points.shape[0], dtype=torch.long),
                          lidar2img.to(torch.float64).reshape(1, 3, 4), image_size, eps=eps)
    return proj.valid[:, 0]
