"""Readers for KITTI-format radar/LiDAR detection datasets (View-of-Delft, TJ4DRadSet, KITTI).

What this module reads (see ``docs/real-data.md`` for the folder layouts):

* point clouds: ``velodyne/<id>.bin``, float32 little-endian ``N x C`` with ``C`` given by a
  :class:`PointFormat` (VoD radar 7, TJ4DRadSet radar 8, KITTI LiDAR 4);
* calibration: ``calib/<id>.txt`` (``P2``, ``R0_rect``, ``Tr_velo_to_cam``) -> ``lidar2img``
  ``= P2 @ R0_rect(4x4) @ Tr_velo_to_cam(4x4)`` (3 x 4, float64), the matrix the library's projector
  takes (OpenCV pixels, pixel ``i``'s centre at ``i``);
* labels: ``label_2/<id>.txt`` (KITTI object lines in the rectified camera frame), converted to the
  library's box convention ``(x, y, z, dx, dy, dz, yaw)`` in the sensor frame (z = box centre, yaw
  about +z, dx along the heading) and back;
* images: ``image_2/<id>.png|jpg`` as a ``(3, H, W)`` uint8 tensor (pillow).

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

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.geometry import project_points

__all__ = [
    "PointFormat",
    "VOD_RADAR",
    "TJ4D_RADAR",
    "KITTI_LIDAR",
    "VOD_CLASSES",
    "TJ4D_CLASSES",
    "KITTI_CLASSES",
    "Calibration",
    "parse_calibration",
    "read_calibration",
    "KittiObjects",
    "parse_labels",
    "read_labels",
    "read_points",
    "read_image",
    "camera_boxes_to_sensor",
    "sensor_boxes_to_camera",
    "camera_box_corners",
    "sensor_box_corners",
    "camera_box_corners_in_sensor",
    "transform_points",
    "project_boxes_2d",
    "points_in_image",
    "Frame",
    "FramePaths",
    "KittiFormatDataset",
    "frames_to_batch",
]

PathLike = Union[str, Path]


# --------------------------------------------------------------------------------------------------
# Point formats
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PointFormat:
    """Channel layout of a ``velodyne/<id>.bin`` file and the input features a detector uses.

    Args:
        name: a label for messages.
        channels: names of the ``C`` float32 columns stored in the file, ``x, y, z`` first.
        features: the columns (by name, in order) that form the network input; ``x, y, z`` first.
    """

    name: str
    channels: Tuple[str, ...]
    features: Tuple[str, ...]

    def __post_init__(self) -> None:
        if tuple(self.channels[:3]) != ("x", "y", "z"):
            raise MSSFError(f"channels: expected x, y, z first, got {self.channels}")
        if tuple(self.features[:3]) != ("x", "y", "z"):
            raise MSSFError(f"features: expected x, y, z first, got {self.features}")
        missing = [f for f in self.features if f not in self.channels]
        if missing:
            raise MSSFError(f"features: expected names from channels {self.channels}, got unknown {missing}")

    @property
    def num_channels(self) -> int:
        return len(self.channels)

    @property
    def feature_index(self) -> List[int]:
        return [self.channels.index(f) for f in self.features]

    def select(self, raw: Tensor) -> Tensor:
        """``(P, C)`` raw columns -> ``(P, F)`` input features."""
        return raw[:, self.feature_index]


#: View-of-Delft radar (``radar``, ``radar_3frames``, ``radar_5frames``): the paper uses all 7 channels.
VOD_RADAR = PointFormat(
    "vod_radar",
    ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time"),
    ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time"),
)
#: TJ4DRadSet radar. The paper's input is ``[x, y, z, v_rc, Power]``; the files hold only the raw radial
#: velocity ``V_r`` and no ego-motion to compensate it, so ``v_r`` stands in for ``v_rc``. Define your
#: own :class:`PointFormat` with a compensated column when you have one.
TJ4D_RADAR = PointFormat(
    "tj4d_radar",
    ("x", "y", "z", "v_r", "range", "power", "alpha", "beta"),
    ("x", "y", "z", "v_r", "power"),
)
#: KITTI LiDAR (HDL-64): ``x, y, z, reflectance``.
KITTI_LIDAR = PointFormat("kitti_lidar", ("x", "y", "z", "reflectance"), ("x", "y", "z", "reflectance"))

#: Evaluated classes (0-based labels in this order; any other type gets label -1).
VOD_CLASSES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
TJ4D_CLASSES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist", "Truck")
KITTI_CLASSES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")


def read_points(path: PathLike, point_format: PointFormat) -> Tensor:
    """Read a float32 little-endian ``N x C`` point file.

    Returns:
        ``(P, C)`` float32 tensor with the columns of ``point_format.channels``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point file not found: {path}")
    data = np.fromfile(path, dtype="<f4")
    c = point_format.num_channels
    if data.size % c:
        raise MSSFError(
            f"{path}: expected a multiple of {c} float32 values ({point_format.name}: {point_format.channels}), "
            f"got {data.size} values ({path.stat().st_size} bytes)"
        )
    return torch.from_numpy(data.reshape(-1, c).astype(np.float32))


def read_image(path: PathLike) -> Tensor:
    """Read an image as a ``(3, H, W)`` uint8 RGB tensor (needs pillow)."""
    try:
        from PIL import Image
    except ImportError as exc:  # pragma: no cover - pillow is in the examples extra
        raise ImportError("reading images needs pillow: pip install 'mssf-blocks[examples]'") from exc
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    with Image.open(path) as im:
        arr = np.asarray(im.convert("RGB"), dtype=np.uint8)
    return torch.from_numpy(arr.copy()).permute(2, 0, 1).contiguous()


def _image_size(path: Path) -> Tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        w, h = im.size
    return int(h), int(w)


# --------------------------------------------------------------------------------------------------
# Calibration
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Calibration:
    """KITTI calibration of one frame (float64).

    Attributes:
        P2: ``(3, 4)`` rectified camera projection.
        R0_rect: ``(3, 3)`` rectifying rotation (identity when the file has none).
        Tr_velo_to_cam: ``(3, 4)`` sensor (LiDAR or radar) to camera.
    """

    P2: Tensor
    R0_rect: Tensor
    Tr_velo_to_cam: Tensor

    @property
    def sensor_to_camera(self) -> Tensor:
        """``(4, 4)`` ``R0_rect(4x4) @ Tr_velo_to_cam(4x4)``: sensor to rectified camera frame."""
        r0 = torch.eye(4, dtype=torch.float64)
        r0[:3, :3] = self.R0_rect
        tr = torch.eye(4, dtype=torch.float64)
        tr[:3, :] = self.Tr_velo_to_cam
        return r0 @ tr

    @property
    def camera_to_sensor(self) -> Tensor:
        """``(4, 4)`` inverse of :attr:`sensor_to_camera`."""
        return torch.linalg.inv(self.sensor_to_camera)

    @property
    def lidar2img(self) -> Tensor:
        """``(3, 4)`` ``P2 @ R0_rect(4x4) @ Tr_velo_to_cam(4x4)``: sensor points to ``(u*d, v*d, d)``."""
        return self.P2 @ self.sensor_to_camera


_CALIB_KEYS = {
    "P2": ("P2",),
    "R0_rect": ("R0_rect", "R_rect", "R0"),
    "Tr_velo_to_cam": ("Tr_velo_to_cam", "Tr_velo_cam"),
}


def parse_calibration(text: str, source: str = "<calibration text>") -> Calibration:
    """Parse KITTI calibration text (``key: v1 v2 ...`` lines; keys with no values are ignored).

    ``R0_rect`` may be absent (identity); ``P2`` and ``Tr_velo_to_cam`` are required.
    """
    values: Dict[str, List[float]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise MSSFError(f"{source}:{lineno}: expected 'key: values', got {line.strip()!r}")
        key, rest = line.split(":", 1)
        try:
            nums = [float(v) for v in rest.split()]
        except ValueError:
            raise MSSFError(f"{source}:{lineno}: expected numbers after {key!r}, got {rest.strip()!r}") from None
        if nums:
            values[key.strip()] = nums

    def get(name: str, size: int, required: bool) -> Optional[Tensor]:
        for alias in _CALIB_KEYS[name]:
            if alias in values:
                nums = values[alias]
                if len(nums) != size:
                    raise MSSFError(f"{source}: expected {size} values for {alias}, got {len(nums)}")
                return torch.tensor(nums, dtype=torch.float64)
        if required:
            raise MSSFError(f"{source}: expected a {name} line (3x4 = 12 values), found keys {sorted(values)}")
        return None

    p2 = get("P2", 12, True).reshape(3, 4)
    tr = get("Tr_velo_to_cam", 12, True).reshape(3, 4)
    r0 = get("R0_rect", 9, False)
    r0 = torch.eye(3, dtype=torch.float64) if r0 is None else r0.reshape(3, 3)
    return Calibration(P2=p2, R0_rect=r0, Tr_velo_to_cam=tr)


def read_calibration(path: PathLike) -> Calibration:
    """Read ``calib/<id>.txt``; see :func:`parse_calibration`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    return parse_calibration(path.read_text(), source=str(path))


# --------------------------------------------------------------------------------------------------
# Labels
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class KittiObjects:
    """The objects of one ``label_2`` file, in the rectified camera frame (G objects).

    Attributes:
        names: ``G`` type strings as written (``Car``, ``Cyclist``, ``DontCare``, ``bicycle``...).
        truncation: ``(G,)`` float64.
        occlusion: ``(G,)`` int64.
        alpha: ``(G,)`` float64 observation angle.
        boxes_2d: ``(G, 4)`` float64 ``(left, top, right, bottom)`` pixels.
        dimensions: ``(G, 3)`` float64 ``(h, w, l)`` metres (file order).
        location: ``(G, 3)`` float64 bottom-face centre in the camera frame.
        rotation_y: ``(G,)`` float64 rotation about camera Y.
        score: ``(G,)`` float64 16th column when present (VoD writes 1), else ``None``.
    """

    names: List[str]
    truncation: Tensor
    occlusion: Tensor
    alpha: Tensor
    boxes_2d: Tensor
    dimensions: Tensor
    location: Tensor
    rotation_y: Tensor
    score: Optional[Tensor] = None

    def __len__(self) -> int:
        return len(self.names)


def parse_labels(text: str, source: str = "<label text>") -> KittiObjects:
    """Parse KITTI label lines (15 fields, or 16 with a score)."""
    rows, names, scores = [], [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        f = line.split()
        if not f:
            continue
        if len(f) not in (15, 16):
            raise MSSFError(f"{source}:{lineno}: expected 15 or 16 fields in a KITTI label line, got {len(f)}")
        try:
            nums = [float(v) for v in f[1:15]]
            if len(f) == 16:
                scores.append(float(f[15]))
        except ValueError:
            raise MSSFError(f"{source}:{lineno}: expected numbers after the type, got {line.strip()!r}") from None
        names.append(f[0])
        rows.append(nums)
    if scores and len(scores) != len(rows):
        raise MSSFError(f"{source}: expected a score on every line or on none, got {len(scores)} of {len(rows)}")
    t = torch.tensor(rows, dtype=torch.float64).reshape(-1, 14)
    return KittiObjects(
        names=names,
        truncation=t[:, 0].clone(),
        occlusion=t[:, 1].round().long(),
        alpha=t[:, 2].clone(),
        boxes_2d=t[:, 3:7].clone(),
        dimensions=t[:, 7:10].clone(),
        location=t[:, 10:13].clone(),
        rotation_y=t[:, 13].clone(),
        score=torch.tensor(scores, dtype=torch.float64) if scores else None,
    )


def read_labels(path: PathLike) -> KittiObjects:
    """Read ``label_2/<id>.txt``; see :func:`parse_labels`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"label file not found: {path}")
    return parse_labels(path.read_text(), source=str(path))


# --------------------------------------------------------------------------------------------------
# Box conversions
# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
# Frames and datasets
# --------------------------------------------------------------------------------------------------
@dataclass
class Frame:
    """One frame of a KITTI-format dataset.

    Attributes:
        frame_id: the file stem, e.g. ``"00549"``.
        points: ``(P, F)`` float32 input features (``point_format.features``, x, y, z first).
        raw_points: ``(P, C)`` float32 all stored channels.
        point_format: the :class:`PointFormat` used.
        image: ``(3, H, W)`` uint8 RGB, or ``None`` when not loaded.
        image_size: ``(H, W)``.
        calib: the :class:`Calibration`.
        lidar2img: ``(3, 4)`` float64 sensor to pixel.
        objects: all label lines (camera frame), or ``None`` without labels.
        boxes: ``(G, 7)`` float64 sensor boxes for every label line (``DontCare`` too).
        labels: ``(G,)`` int64 index into ``class_names`` (-1 for other types).
        class_names: the evaluated classes.
    """

    frame_id: str
    points: Tensor
    raw_points: Tensor
    point_format: PointFormat
    image: Optional[Tensor]
    image_size: Tuple[int, int]
    calib: Calibration
    lidar2img: Tensor
    objects: Optional[KittiObjects]
    boxes: Tensor
    labels: Tensor
    class_names: Tuple[str, ...] = field(default=VOD_CLASSES)

    @property
    def gt_boxes(self) -> Tensor:
        """``(G', 7)`` boxes of the evaluated classes only."""
        return self.boxes[self.labels >= 0]

    @property
    def gt_labels(self) -> Tensor:
        """``(G',)`` 0-based labels of the evaluated classes only."""
        return self.labels[self.labels >= 0]


@dataclass(frozen=True)
class FramePaths:
    """Files of one frame (``image``/``label`` may be ``None`` when the folder does not exist)."""

    points: Path
    calib: Path
    image: Optional[Path]
    label: Optional[Path]


_IMAGE_EXTS = (".png", ".jpg", ".jpeg")


class KittiFormatDataset:
    """Locate and read frames of a KITTI-format dataset.

    Layouts (``S`` = ``sensor``; first match wins):

    * nested (VoD release): ``root/S/training/{velodyne,calib,image_2,label_2}``, ``root/S/ImageSets``;
    * standard (KITTI, TJ4DRadSet; ``sensor=None``): ``root/training/{...}``, ``root/ImageSets``;
    * flat: ``root/S/{velodyne,calib}`` (or ``root/{velodyne,calib}`` with ``sensor=None``) with
      ``image_2``/``label_2`` beside them or one level up (``../shared/realdata/vod`` uses
      ``radar/velodyne``, ``radar/calib``, ``image_2``, ``label_2``).

    ``split="test"`` reads ``testing/`` when it exists. Split files are ``ImageSets/<split>.txt`` beside
    ``training/`` (or in ``root/ImageSets``, or ``root/lidar/ImageSets`` as in the VoD release).

    Args:
        root: dataset root.
        point_format: :data:`VOD_RADAR`, :data:`TJ4D_RADAR`, :data:`KITTI_LIDAR` or your own.
        sensor: sub-folder (VoD: ``"radar"``, ``"radar_3frames"``, ``"radar_5frames"``, ``"lidar"``);
            ``None`` for roots holding ``training/`` or ``velodyne/`` directly.
        split: ``None`` (every point file) or the name of a split file (``"train"``, ``"val"``, ...).
        class_names: classes that get labels ``0..K-1``.
        load_image: read the image into :attr:`Frame.image` (otherwise only its size).

    Raises:
        FileNotFoundError: naming every path tried when the layout, a split file or a frame's file is
            missing.
    """

    def __init__(
        self,
        root: PathLike,
        point_format: PointFormat = VOD_RADAR,
        sensor: Optional[str] = "radar",
        split: Optional[str] = None,
        class_names: Sequence[str] = VOD_CLASSES,
        load_image: bool = True,
    ) -> None:
        if not isinstance(point_format, PointFormat):
            raise MSSFError(f"point_format: expected a PointFormat, got {type(point_format).__name__}")
        self.root = Path(root)
        self.point_format = point_format
        self.sensor = sensor
        self.split = split
        self.class_names = tuple(class_names)
        self.load_image = bool(load_image)
        if not self.root.is_dir():
            raise FileNotFoundError(f"dataset root not found: {self.root}")
        self.data_dir, self.layout = self._find_data_dir()
        search = [self.data_dir] if self.layout != "flat" else [self.data_dir, self.data_dir.parent]
        self.calib_dir = self._find_dir("calib", search, required=True)
        self.image_dir = self._find_dir("image_2", search, required=False)
        self.label_dir = self._find_dir("label_2", search, required=False)
        self.frame_ids = self._frame_ids()

    # -- layout ------------------------------------------------------------------------------------
    def _find_data_dir(self) -> Tuple[Path, str]:
        base = self.root / self.sensor if self.sensor else self.root
        subsets = ["testing", "training"] if self.split == "test" else ["training"]
        tried = []
        for subset in subsets:
            cand = base / subset
            tried.append(cand / "velodyne")
            if (cand / "velodyne").is_dir():
                return cand, "nested"
        tried.append(base / "velodyne")
        if (base / "velodyne").is_dir():
            return base, "flat"
        raise FileNotFoundError(
            f"no point-cloud folder for sensor={self.sensor!r} under {self.root}; tried: "
            + ", ".join(str(t) for t in tried)
        )

    @staticmethod
    def _find_dir(name: str, search: Sequence[Path], required: bool) -> Optional[Path]:
        for d in search:
            if (d / name).is_dir():
                return d / name
        if required:
            raise FileNotFoundError(f"no {name}/ folder; tried: " + ", ".join(str(d / name) for d in search))
        return None

    def _frame_ids(self) -> List[str]:
        points_dir = self.data_dir / "velodyne"
        available = sorted(p.stem for p in points_dir.glob("*.bin"))
        if self.split is None:
            return available
        cands = []
        # the VoD release keeps its split files in lidar/ImageSets only; OpenPCDet copies them per sensor
        for d in (self.data_dir.parent, self.data_dir, self.root, self.root / "lidar"):
            f = d / "ImageSets" / f"{self.split}.txt"
            if f not in cands:
                cands.append(f)
        for f in cands:
            if f.is_file():
                ids = [line.strip() for line in f.read_text().splitlines() if line.strip()]
                have = set(available)
                missing = [i for i in ids if i not in have]
                if missing:
                    raise FileNotFoundError(
                        f"split file {f} lists {len(missing)} frames without a point file in {points_dir}, "
                        f"e.g. {missing[:5]}"
                    )
                return ids
        raise FileNotFoundError(f"split file for split={self.split!r} not found; tried: " + ", ".join(map(str, cands)))

    # -- access --------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, index: int) -> Frame:
        return self.load(self.frame_ids[index])

    def paths(self, frame_id: str) -> FramePaths:
        """The files of ``frame_id`` (image/label ``None`` when their folder is absent)."""
        image = None
        if self.image_dir is not None:
            image = next((self.image_dir / f"{frame_id}{e}" for e in _IMAGE_EXTS
                          if (self.image_dir / f"{frame_id}{e}").is_file()), self.image_dir / f"{frame_id}.png")
        label = None if self.label_dir is None else self.label_dir / f"{frame_id}.txt"
        return FramePaths(points=self.data_dir / "velodyne" / f"{frame_id}.bin",
                          calib=self.calib_dir / f"{frame_id}.txt", image=image, label=label)

    def load(self, frame_id: str, with_labels: bool = True) -> Frame:
        """Read one frame.

        Args:
            frame_id: file stem.
            with_labels: read ``label_2`` (``False`` for test splits without labels: empty boxes).
        """
        frame_id = str(frame_id)
        p = self.paths(frame_id)
        raw = read_points(p.points, self.point_format)
        calib = read_calibration(p.calib)
        if p.image is None:
            raise FileNotFoundError(f"no image_2/ folder for frame {frame_id} (searched near {self.data_dir})")
        if not p.image.is_file():
            raise FileNotFoundError(f"image not found: {p.image.with_suffix('')}.{{png,jpg,jpeg}}")
        image = read_image(p.image) if self.load_image else None
        size = (int(image.shape[1]), int(image.shape[2])) if image is not None else _image_size(p.image)
        objects = None
        boxes = torch.zeros(0, 7, dtype=torch.float64)
        labels = torch.zeros(0, dtype=torch.long)
        if with_labels:
            if p.label is None:
                raise FileNotFoundError(f"no label_2/ folder for frame {frame_id} (searched near {self.data_dir}); "
                                        "use with_labels=False for unlabelled splits")
            objects = read_labels(p.label)
            boxes = camera_boxes_to_sensor(objects.location, objects.dimensions, objects.rotation_y, calib)
            labels = torch.tensor([self.class_names.index(n) if n in self.class_names else -1
                                   for n in objects.names], dtype=torch.long)
        return Frame(
            frame_id=frame_id, points=self.point_format.select(raw), raw_points=raw,
            point_format=self.point_format, image=image, image_size=size, calib=calib,
            lidar2img=calib.lidar2img, objects=objects, boxes=boxes, labels=labels,
            class_names=self.class_names,
        )

    def __repr__(self) -> str:
        return (f"KittiFormatDataset(root={str(self.root)!r}, point_format={self.point_format.name}, "
                f"sensor={self.sensor!r}, split={self.split!r}, layout={self.layout!r}, frames={len(self)})")


def frames_to_batch(frames: Sequence[Frame], dtype: torch.dtype = torch.float32):
    """Stack frames into the examples' :class:`~mssf_examples.data.RadarCameraBatch` (one camera).

    Points keep their input features (``Frame.points``); images become ``(B, 1, 3, H, W)`` floats in
    ``[0, 1]``; ``lidar2img`` is ``(B, 1, 3, 4)``; ground truth holds the evaluated classes only
    (:attr:`Frame.gt_boxes`, :attr:`Frame.gt_labels`). All images must have one size.
    """
    from .data import RadarCameraBatch

    frames = list(frames)
    if not frames:
        raise MSSFError("frames: expected at least one Frame, got none")
    sizes = {f.image_size for f in frames}
    if len(sizes) != 1:
        raise MSSFError(f"frames: expected one image size to stack, got {sorted(sizes)}")
    if any(f.image is None for f in frames):
        raise MSSFError("frames: expected loaded images (KittiFormatDataset(load_image=True))")
    return RadarCameraBatch(
        points=[f.points.to(dtype) for f in frames],
        lidar2img=torch.stack([f.lidar2img for f in frames])[:, None].to(dtype),
        images=torch.stack([f.image for f in frames])[:, None].to(dtype) / 255.0,
        gt_boxes=[f.gt_boxes.to(dtype) for f in frames],
        gt_labels=[f.gt_labels for f in frames],
    )
