"""Deterministic synthetic 4D-radar + camera scenes that reproduce the effects the MSSF paper builds on.

Real 4D-radar data (VoD, TJ4DRadSet) cannot ship with the library, yet the examples need data on which
an image really helps a radar detector. These scenes are built so that it does, for the reasons the
paper gives (Sec. I, IV-C, Fig. 1):

* **Radar alone is ambiguous.** Static clutter (poles, walls, guard rails, car-sized and person-sized
  boxes) returns points with the same point counts, RCS and (zero) Doppler as static cars, pedestrians
  and cyclists; a pole looks like a pedestrian. Pedestrians and cyclists have similar radar
  footprints (a cyclist's returns come mostly from the rider). Moving objects stand out by Doppler, as
  on real radar.
* **The camera disambiguates.** Cars, pedestrians and cyclists render with class-specific colour, shape
  and texture (car bodies with windows, wheels and lamps; people with head, torso and legs; riders on
  two wheels); clutter renders in the desaturated greys of the background.
* **3D-blurred points.** Multipath ghosts behind objects (carrying the object's Doppler), clutter behind
  objects that leaks through occlusion, and noise points project into an object's 2D box without lying
  in its 3D box (paper Fig. 1); ``Scene.blurred_point_mask`` marks them.
* **Lighting** normal / dark / dazzle (TJ4DRadSet analysis, Sec. IV-D) with the paper's shares
  60 / 15 / 25 % by default.

Geometry follows VoD: radar frame ``x`` forward, ``y`` left, ``z`` up, radar behind the bumper at
``radar_height`` above a flat ground, a camera above and behind it with VoD's intrinsics scaled from
1936 x 1216 to a small image, ``multi-scan`` accumulation with ego-motion compensation and a time
index. Points use VoD's channel order ``[x, y, z, RCS, v_r, v_rc, t]``.

Everything is generated with numpy from one integer seed, so a scene is a pure function of
``(seed, config)``. See ``docs/scenes.md`` for pictures and limits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

__all__ = [
    "CLASS_NAMES",
    "CLUTTER_KINDS",
    "LIGHTING_CONDITIONS",
    "POINT_SOURCES",
    "SceneConfig",
    "Scene",
    "generate_scene",
    "scene_seed",
    "SyntheticDataset",
    "box_corners",
    "points_in_box",
]

#: Object classes, indexed by ``Scene.gt_labels``.
CLASS_NAMES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
#: Clutter kinds, indexed by ``Scene.clutter_kinds``.
CLUTTER_KINDS: Tuple[str, ...] = ("pole", "car_like", "small_box", "wall", "guard_rail")
#: Lighting conditions, the values of ``Scene.lighting``.
LIGHTING_CONDITIONS: Tuple[str, ...] = ("normal", "dark", "dazzle")
#: Codes of ``Scene.point_source``.
POINT_SOURCES: Tuple[str, ...] = ("object", "ghost", "clutter", "noise")

_SPLITS = {"train": 0, "val": 1, "test": 2}

# Per-class radar signature: expected points per scan at 10 m, RCS mean / spread (dBsm), share moving,
# speed range (m/s). Pedestrian and cyclist are deliberately alike; clutter copies these (see below).
_CLASS_RADAR = {
    0: dict(points=6.0, rcs=(6.0, 4.0), moving=0.35, speed=(2.0, 9.0)),
    1: dict(points=2.2, rcs=(-1.0, 3.5), moving=0.6, speed=(0.6, 2.2)),
    2: dict(points=2.4, rcs=(0.0, 3.5), moving=0.7, speed=(1.5, 6.0)),
}
# Clutter radar signatures: pole ~ pedestrian, car_like ~ static car, small_box ~ pedestrian/cyclist.
_CLUTTER_RADAR = {
    0: dict(points=2.2, rcs=(-0.5, 3.5)),
    1: dict(points=6.0, rcs=(5.5, 4.0)),
    2: dict(points=2.3, rcs=(-0.5, 3.5)),
    3: dict(points=1.0, rcs=(3.0, 4.5)),  # per metre of wall length
    4: dict(points=0.8, rcs=(4.0, 4.5)),  # per metre of rail length
}


@dataclass
class SceneConfig:
    """Settings of the synthetic scene generator (all lengths in metres, angles in degrees).

    Attributes:
        point_cloud_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` of kept radar points and of
            object centres.
        image_size: ``(H, W)`` of the rendered image.
        full_image_size: ``(H, W)`` of the camera the intrinsics refer to (VoD: 1216 x 1936).
        full_intrinsics: ``(fx, fy, cx, cy)`` at ``full_image_size`` (VoD's camera); scaled to
            ``image_size``.
        radar_height: height of the radar (sensor-frame origin) above the flat ground.
        camera_position: camera centre in the sensor frame (above and behind the bumper radar).
        radar_fov: full horizontal field of view of the radar; points outside are dropped.
        num_scans: accumulated radar scans (VoD: 5); ``t`` is ``0`` for the newest, ``-k`` for k scans ago.
        scan_period: seconds between scans.
        num_objects: inclusive ``(min, max)`` number of cars + pedestrians + cyclists.
        class_probs: probabilities of car, pedestrian, cyclist.
        num_clutter: inclusive ``(min, max)`` number of clutter items.
        clutter_probs: probabilities of the :data:`CLUTTER_KINDS`.
        min_range: closest object/clutter distance from the radar.
        ego_speed: ``(min, max)`` ego speed along +x; ``ego_static_prob`` of standing still.
        range_noise, azimuth_noise, elevation_noise: radar position noise (std, spherical).
        doppler_noise: std of measured radial velocities; ``micro_doppler`` extra std for moving
            pedestrians and cyclists (limbs, wheels).
        rcs_noise: per-point RCS std around the item's RCS.
        points_scale: multiplies every expected point count.
        ghost_rate: expected multipath ghost points per object and scan (behind the object).
        occlusion_leak: probability that a radar point occluded by another item is still measured;
            ``occlusion_leak_people`` the same when only pedestrians / cyclists are in the way.
        noise_points: expected background noise points per scan; ``noise_doppler_outlier_prob`` of them
            get a random Doppler.
        lighting_probs: probabilities of normal, dark, dazzle (TJ4DRadSet test set: 60 / 15 / 25 %).
        lighting: force one lighting condition (``None`` draws from ``lighting_probs``).
        dark_gain: ``(min, max)`` brightness factor of dark images; ``dark_noise`` their noise std.
        image_noise: pixel noise std of every image.
    """

    point_cloud_range: Tuple[float, float, float, float, float, float] = (0.0, -12.8, -3.0, 25.6, 12.8, 2.0)
    image_size: Tuple[int, int] = (152, 240)
    full_image_size: Tuple[int, int] = (1216, 1936)
    full_intrinsics: Tuple[float, float, float, float] = (1495.47, 1495.47, 961.27, 624.90)
    radar_height: float = 0.5
    camera_position: Tuple[float, float, float] = (-0.6, 0.0, 0.9)
    radar_fov: float = 120.0
    num_scans: int = 5
    scan_period: float = 0.1
    num_objects: Tuple[int, int] = (5, 12)
    class_probs: Tuple[float, float, float] = (0.45, 0.3, 0.25)
    num_clutter: Tuple[int, int] = (5, 10)
    clutter_probs: Tuple[float, float, float, float, float] = (0.3, 0.2, 0.25, 0.15, 0.1)
    min_range: float = 3.0
    ego_speed: Tuple[float, float] = (0.0, 8.0)
    ego_static_prob: float = 0.3
    range_noise: float = 0.05
    azimuth_noise: float = 0.5
    elevation_noise: float = 1.0
    doppler_noise: float = 0.1
    micro_doppler: float = 0.25
    rcs_noise: float = 3.0
    points_scale: float = 1.0
    ghost_rate: float = 0.3
    occlusion_leak: float = 0.1
    occlusion_leak_people: float = 0.6
    noise_points: float = 10.0
    noise_doppler_outlier_prob: float = 0.15
    lighting_probs: Tuple[float, float, float] = (0.6, 0.15, 0.25)
    lighting: Optional[str] = None
    dark_gain: Tuple[float, float] = (0.12, 0.25)
    dark_noise: float = 0.03
    image_noise: float = 0.01

    def __post_init__(self) -> None:
        r = tuple(float(v) for v in self.point_cloud_range)
        if len(r) != 6 or not (r[0] < r[3] and r[1] < r[4] and r[2] < r[5]):
            raise MSSFError(f"point_cloud_range: expected (x_min, y_min, z_min, x_max, y_max, z_max) with "
                            f"min < max, got {self.point_cloud_range!r}")
        self.point_cloud_range = r
        for name in ("image_size", "full_image_size"):
            v = getattr(self, name)
            if len(v) != 2 or any(isinstance(s, bool) or not isinstance(s, int) or s < 8 for s in v):
                raise MSSFError(f"{name}: expected (H, W) ints >= 8, got {v!r}")
        if len(self.full_intrinsics) != 4 or min(self.full_intrinsics[:2]) <= 0:
            raise MSSFError(f"full_intrinsics: expected (fx, fy, cx, cy) with fx, fy > 0, got {self.full_intrinsics!r}")
        if not (-r[2] > self.radar_height >= 0.0):
            raise MSSFError(f"radar_height: expected 0 <= radar_height < -z_min ({-r[2]}), got {self.radar_height}")
        if len(self.camera_position) != 3:
            raise MSSFError(f"camera_position: expected (x, y, z), got {self.camera_position!r}")
        if self.camera_position[0] >= self.min_range - 0.5:
            raise MSSFError(f"camera_position: x must be < min_range - 0.5 ({self.min_range - 0.5}) so every "
                            f"object is in front of the camera, got {self.camera_position[0]}")
        if not (0 < self.radar_fov <= 180):
            raise MSSFError(f"radar_fov: expected degrees in (0, 180], got {self.radar_fov}")
        if isinstance(self.num_scans, bool) or not isinstance(self.num_scans, int) or self.num_scans < 1:
            raise MSSFError(f"num_scans: expected a positive int, got {self.num_scans!r}")
        for name in ("num_objects", "num_clutter"):
            lo, hi = getattr(self, name)
            if not (0 <= lo <= hi):
                raise MSSFError(f"{name}: expected (min, max) with 0 <= min <= max, got {(lo, hi)!r}")
        for name, n in (("class_probs", 3), ("clutter_probs", len(CLUTTER_KINDS)), ("lighting_probs", 3)):
            p = np.asarray(getattr(self, name), dtype=np.float64)
            if p.shape != (n,) or (p < 0).any() or p.sum() <= 0:
                raise MSSFError(f"{name}: expected {n} non-negative probabilities with a positive sum, "
                                f"got {getattr(self, name)!r}")
        if self.lighting is not None and self.lighting not in LIGHTING_CONDITIONS:
            raise MSSFError(f"lighting: expected None or one of {LIGHTING_CONDITIONS}, got {self.lighting!r}")
        if not (0 < self.min_range < r[3] - 1.0):
            raise MSSFError(f"min_range: expected 0 < min_range < x_max - 1 ({r[3] - 1.0}), got {self.min_range}")
        for name in ("scan_period", "range_noise", "azimuth_noise", "elevation_noise", "doppler_noise",
                     "micro_doppler", "rcs_noise", "points_scale", "ghost_rate", "noise_points",
                     "dark_noise", "image_noise", "ego_static_prob", "occlusion_leak",
                     "occlusion_leak_people", "noise_doppler_outlier_prob"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise MSSFError(f"{name}: expected a finite non-negative number, got {v!r}")
        for name in ("ego_static_prob", "occlusion_leak", "occlusion_leak_people", "noise_doppler_outlier_prob"):
            if getattr(self, name) > 1:
                raise MSSFError(f"{name}: expected a probability in [0, 1], got {getattr(self, name)}")
        if not (0 <= self.ego_speed[0] <= self.ego_speed[1]):
            raise MSSFError(f"ego_speed: expected (min, max) with 0 <= min <= max, got {self.ego_speed!r}")
        if not (0 < self.dark_gain[0] <= self.dark_gain[1] <= 1):
            raise MSSFError(f"dark_gain: expected (min, max) in (0, 1], got {self.dark_gain!r}")

    def intrinsics(self) -> np.ndarray:
        """``(3, 3)`` float64 camera matrix scaled to ``image_size`` (OpenCV: pixel i's centre at i)."""
        (h, w), (hf, wf) = self.image_size, self.full_image_size
        fx, fy, cx, cy = self.full_intrinsics
        sx, sy = w / wf, h / hf
        # Scaling keeps pixel *edges* aligned: centre i <-> [i - 0.5, i + 0.5].
        return np.array([[fx * sx, 0.0, (cx + 0.5) * sx - 0.5], [0.0, fy * sy, (cy + 0.5) * sy - 0.5],
                         [0.0, 0.0, 1.0]])

    def sensor_to_camera(self) -> np.ndarray:
        """``(4, 4)`` float64 rigid transform from the radar frame (x fwd, y left, z up) to OpenCV camera."""
        rot = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        out = np.eye(4)
        out[:3, :3] = rot
        out[:3, 3] = -rot @ np.asarray(self.camera_position, dtype=np.float64)
        return out

    def lidar2img(self) -> np.ndarray:
        """``(3, 4)`` float64 projection of homogeneous sensor points to ``(u*d, v*d, d)``."""
        return self.intrinsics() @ self.sensor_to_camera()[:3]


@dataclass
class Scene:
    """One synthetic radar + camera frame (all tensors on CPU).

    Attributes:
        points: ``(P, 7)`` float32 ``[x, y, z, RCS, v_r, v_rc, t]`` in the sensor frame; ``v_r`` relative
            and ``v_rc`` ego-compensated radial velocity (positive = moving away), ``t`` the scan index
            (``0`` newest, ``-1`` one scan earlier, ...).
        image: ``(3, H, W)`` float32 RGB in ``[0, 1]``.
        lidar2img: ``(3, 4)`` float64 sensor -> pixels, ``(u*d, v*d, d)``, OpenCV pixel centres.
        intrinsics: ``(3, 3)`` float64 camera matrix; sensor_to_camera: ``(4, 4)`` float64.
        gt_boxes: ``(G, 7)`` float32 ``(x, y, z_centre, dx, dy, dz, yaw)`` at the newest scan.
        gt_labels: ``(G,)`` int64, indices into :data:`CLASS_NAMES`.
        gt_boxes_2d: ``(G, 4)`` float32 ``(left, top, right, bottom)``: the box's 8 projected corners'
            extent clipped to ``[0, W - 1] x [0, H - 1]``.
        gt_velocity: ``(G, 2)`` float32 absolute ``(vx, vy)``; gt_moving: ``(G,)`` bool.
        clutter_boxes: ``(K, 7)`` float32; clutter_kinds: ``(K,)`` int64 into :data:`CLUTTER_KINDS`.
        lighting: one of :data:`LIGHTING_CONDITIONS`.
        blurred_point_mask: ``(P,)`` bool, projects (depth > 0) into some GT 2D box but lies in no GT 3D box.
        point_is_clutter: ``(P,)`` bool, returns of clutter items.
        point_source: ``(P,)`` int64 into :data:`POINT_SOURCES` (object surface, multipath ghost, clutter,
            background noise).
        point_object_index: ``(P,)`` int64 GT index of object and ghost points, ``-1`` otherwise.
        instance_map: ``(H, W)`` int64 which item is visible at each pixel: ``-1`` background,
            ``0..G-1`` objects, ``G..G+K-1`` clutter (before lighting).
        ego_velocity: ``(2,)`` float32 ego ``(vx, vy)``.
        seed: the seed the scene was generated from.
    """

    points: Tensor
    image: Tensor
    lidar2img: Tensor
    intrinsics: Tensor
    sensor_to_camera: Tensor
    gt_boxes: Tensor
    gt_labels: Tensor
    gt_boxes_2d: Tensor
    gt_velocity: Tensor
    gt_moving: Tensor
    clutter_boxes: Tensor
    clutter_kinds: Tensor
    lighting: str
    blurred_point_mask: Tensor
    point_is_clutter: Tensor
    point_source: Tensor
    point_object_index: Tensor
    instance_map: Tensor
    ego_velocity: Tensor
    seed: int

    @property
    def image_size(self) -> Tuple[int, int]:
        """``(H, W)``."""
        return int(self.image.shape[1]), int(self.image.shape[2])

    def to_batch(self):
        """A one-sample :class:`mssf_examples.data.RadarCameraBatch` (use :meth:`collate` for several)."""
        return Scene.collate([self])

    @staticmethod
    def collate(scenes: Sequence["Scene"]):
        """Stack scenes into a :class:`mssf_examples.data.RadarCameraBatch` with ``V = 1`` camera."""
        from .data import RadarCameraBatch  # local: keep scenes importable without the detector code

        if len(scenes) == 0:
            raise MSSFError("scenes: expected at least one Scene, got an empty sequence")
        return RadarCameraBatch(
            points=[s.points for s in scenes],
            lidar2img=torch.stack([s.lidar2img.float() for s in scenes])[:, None],
            images=torch.stack([s.image for s in scenes])[:, None],
            gt_boxes=[s.gt_boxes for s in scenes],
            gt_labels=[s.gt_labels for s in scenes],
        )


# ----------------------------------------------------------------------------------------------------
# Geometry helpers (numpy, float64)
# ----------------------------------------------------------------------------------------------------


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """``(G, 8, 3)`` corners of ``(G, 7)`` boxes ``(x, y, z_centre, dx, dy, dz, yaw)``.

    Corner ``k`` has local signs ``(+-dx/2, +-dy/2, +-dz/2)`` with bits ``(k>>2, k>>1, k) & 1`` (1 = minus).
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    bits = np.array([[(k >> 2) & 1, (k >> 1) & 1, k & 1] for k in range(8)], dtype=np.float64)
    local = (0.5 - bits)[None] * boxes[:, None, 3:6]
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    x = c * local[..., 0] - s * local[..., 1]
    y = s * local[..., 0] + c * local[..., 1]
    return np.stack([x, y, local[..., 2]], -1) + boxes[:, None, :3]


def points_in_box(points: np.ndarray, box: np.ndarray, margin: float | np.ndarray = 0.0) -> np.ndarray:
    """``(P,)`` bool: points ``(P, 3+)`` inside one box ``(7,)`` enlarged by ``margin`` on every side."""
    p = np.asarray(points, dtype=np.float64)[:, :3] - np.asarray(box[:3], dtype=np.float64)
    c, s = math.cos(float(box[6])), math.sin(float(box[6]))
    lx, ly = c * p[:, 0] + s * p[:, 1], -s * p[:, 0] + c * p[:, 1]
    m = np.asarray(margin, dtype=np.float64)
    return ((np.abs(lx) <= box[3] / 2 + m) & (np.abs(ly) <= box[4] / 2 + m) & (np.abs(p[:, 2]) <= box[5] / 2 + m))


def _bev_rect(box: np.ndarray, grow: float) -> np.ndarray:
    """``(4, 2)`` BEV corners of a box enlarged by ``grow``."""
    c, s = math.cos(box[6]), math.sin(box[6])
    hx, hy = box[3] / 2 + grow, box[4] / 2 + grow
    local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    return local @ np.array([[c, s], [-s, c]]) + box[:2]


def _bev_overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Separating-axis test of two convex BEV polygons ``(4, 2)``."""
    for poly in (a, b):
        edges = np.roll(poly, -1, 0) - poly
        for n in np.stack([-edges[:, 1], edges[:, 0]], 1):
            pa, pb = a @ n, b @ n
            if pa.max() < pb.min() or pb.max() < pa.min():
                return False
    return True


def _segment_hits_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """``(P, M)`` bool: the segment from the radar (origin) to each point crosses box ``m`` (slab test)."""
    if len(points) == 0 or len(boxes) == 0:
        return np.zeros((len(points), len(boxes)), dtype=bool)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])

    def local(v):  # (P, M, 3) in each box's frame
        x, y = v[..., 0], v[..., 1]
        return np.stack([c * x + s * y, -s * x + c * y, v[..., 2]], -1)

    origin = local(-boxes[None, :, :3] + 0.0 * points[:, None, :3])
    d = local(points[:, None, :3] - boxes[None, :, :3]) - origin
    half = boxes[None, :, 3:6] / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - origin) / d, (half - origin) / d
    # A zero direction component: inside that slab for all t (or never).
    inside = np.abs(origin) <= half
    lo = np.where(d == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2)).max(-1)
    hi = np.where(d == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2)).min(-1)
    return (hi >= np.maximum(lo, 0.0)) & (lo <= 1.0)


# ----------------------------------------------------------------------------------------------------
# Scene layout
# ----------------------------------------------------------------------------------------------------


@dataclass
class _Item:
    box: np.ndarray  # (7,)
    label: int  # class (objects) or clutter kind
    is_object: bool
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    rcs_mean: float = 0.0
    colour: np.ndarray = field(default_factory=lambda: np.zeros(3))
    extra: Dict[str, np.ndarray] = field(default_factory=dict)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6.0) % 6
    f = h * 6.0 - math.floor(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i])


def _class_colour(rng: np.random.Generator, label: int) -> np.ndarray:
    # Class hue families (per-instance jitter): cars red/magenta, pedestrians green/teal, cyclists
    # yellow/orange. Saturated, unlike anything in the background.
    hue = {0: rng.uniform(-0.04, 0.04) % 1.0, 1: rng.uniform(0.3, 0.45), 2: rng.uniform(0.1, 0.16)}[label]
    return _hsv(hue, rng.uniform(0.65, 0.95), rng.uniform(0.6, 0.95))


def _grey(rng: np.random.Generator, lo: float = 0.3, hi: float = 0.7) -> np.ndarray:
    # Background-like: almost no saturation, slight warm/cold tint as in the background.
    return np.clip(rng.uniform(lo, hi) + rng.normal(0.0, 0.012, 3), 0, 1)


def _place(rng, cfg: SceneConfig, items: List[_Item], dims, yaw, z_bottom, kind, tries=40) -> Optional[np.ndarray]:
    """A non-overlapping box; ``kind``: 'view' (inside the camera view) or 'side' (walls along the road)."""
    x0, y0, _, x1, y1, _ = cfg.point_cloud_range
    k = cfg.intrinsics()
    half_fov = math.atan2(cfg.image_size[1] / 2.0, k[0, 0]) - math.radians(3.0)
    for _ in range(tries):
        if kind == "side":
            x = rng.uniform(max(x0, cfg.min_range) + dims[0] / 2 - 1.0, x1 - 1.0)
            y = rng.choice([-1.0, 1.0]) * rng.uniform(4.0, min(12.0, y1 - 0.5))
        else:
            r = rng.uniform(cfg.min_range + dims[0] / 2, x1 - 1.0)
            a = rng.uniform(-half_fov, half_fov)
            x, y = r * math.cos(a), r * math.sin(a)
        box = np.array([x, y, z_bottom + dims[2] / 2, dims[0], dims[1], dims[2], yaw])
        corners = box_corners(box)[0]
        if corners[:, 0].min() < cfg.camera_position[0] + 0.5 or not (y0 <= y <= y1 and x0 <= x <= x1):
            continue
        rect = _bev_rect(box, 0.3)
        radius = math.hypot(box[3] / 2 + 0.3, box[4] / 2 + 0.3)
        # Bounding circles first: most pairs are far apart, and the polygon test is the slow part.
        if all(math.hypot(box[0] - it.box[0], box[1] - it.box[1])
               > radius + math.hypot(it.box[3] / 2 + 0.3, it.box[4] / 2 + 0.3)
               or not _bev_overlap(rect, _bev_rect(it.box, 0.3)) for it in items):
            return box
    return None


def _layout(rng: np.random.Generator, cfg: SceneConfig) -> Tuple[List[_Item], List[_Item]]:
    ground = -cfg.radar_height
    objects: List[_Item] = []
    n_obj = int(rng.integers(cfg.num_objects[0], cfg.num_objects[1] + 1))
    cp = np.asarray(cfg.class_probs, dtype=np.float64)
    for _ in range(n_obj):
        label = int(rng.choice(3, p=cp / cp.sum()))
        if label == 0:
            dims = (rng.normal(3.9, 0.3), rng.normal(1.65, 0.08), rng.normal(1.55, 0.08))
            road = rng.random() < 0.75
        elif label == 1:
            dims = (rng.uniform(0.5, 0.8), rng.uniform(0.5, 0.7), rng.normal(1.72, 0.07))
            road = False
        else:
            dims = (rng.normal(1.76, 0.08), rng.uniform(0.55, 0.7), rng.normal(1.7, 0.06))
            road = rng.random() < 0.6
        yaw = (rng.choice([0.0, math.pi]) + rng.normal(0, 0.08)) if road else rng.uniform(-math.pi, math.pi)
        yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
        box = _place(rng, cfg, objects, dims, yaw, ground, "view")
        if box is None:
            continue
        sig = _CLASS_RADAR[label]
        vel = np.zeros(2)
        if rng.random() < sig["moving"]:
            vel = rng.uniform(*sig["speed"]) * np.array([math.cos(yaw), math.sin(yaw)])
        objects.append(_Item(box, label, True, vel, rng.normal(sig["rcs"][0], sig["rcs"][1]),
                             _class_colour(rng, label)))
    clutter: List[_Item] = []
    n_cl = int(rng.integers(cfg.num_clutter[0], cfg.num_clutter[1] + 1))
    qp = np.asarray(cfg.clutter_probs, dtype=np.float64)
    for _ in range(n_cl):
        kind = int(rng.choice(len(CLUTTER_KINDS), p=qp / qp.sum()))
        road_yaw = rng.normal(0, 0.04)
        where = "view"
        if kind == 0:
            w = rng.uniform(0.15, 0.35)
            dims, yaw = (w, w, rng.uniform(2.5, 4.0)), rng.uniform(-math.pi, math.pi)
        elif kind == 1:
            dims, yaw = (rng.uniform(3.0, 5.0), rng.uniform(1.5, 2.2), rng.uniform(1.2, 2.2)), road_yaw
        elif kind == 2:
            dims, yaw = (rng.uniform(0.5, 1.8), rng.uniform(0.5, 0.8), rng.uniform(1.0, 1.8)), rng.uniform(-math.pi, math.pi)
        elif kind == 3:
            dims, yaw, where = (rng.uniform(4.0, 10.0), 0.3, rng.uniform(1.5, 3.0)), road_yaw, "side"
        else:
            dims, yaw, where = (rng.uniform(5.0, 12.0), 0.15, rng.uniform(0.6, 0.9)), road_yaw, "side"
        box = _place(rng, cfg, objects + clutter, dims, yaw, ground, where)
        if box is None:
            continue
        sig = _CLUTTER_RADAR[kind]
        clutter.append(_Item(box, kind, False, np.zeros(2), rng.normal(sig["rcs"][0], sig["rcs"][1]), _grey(rng)))
    return objects, clutter


# ----------------------------------------------------------------------------------------------------
# Radar
# ----------------------------------------------------------------------------------------------------


def _surface_points(rng: np.random.Generator, box: np.ndarray, n: int, z_frac=(0.05, 0.95)) -> np.ndarray:
    """``(n, 3)`` points uniform on the radar-facing vertical faces of ``box`` (weighted by visible area)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    ax = np.array([[c, s], [-s, c]])  # rows: local x, local y axes in the sensor frame
    # Four vertical faces: (normal axis, sign, half-width along the other axis, half-extent of normal axis).
    normals, centres, tangents, widths = [], [], [], []
    for a in (0, 1):
        for sign in (1.0, -1.0):
            nrm = sign * ax[a]
            normals.append(nrm)
            centres.append(box[:2] + nrm * box[3 + a] / 2)
            tangents.append(ax[1 - a])
            widths.append(box[3 + (1 - a)])
    normals, centres, tangents, widths = map(np.asarray, (normals, centres, tangents, widths))
    view = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cosang = (normals * view).sum(1)
    weight = np.clip(cosang, 0, None) * widths
    if n == 0 or weight.sum() <= 0:
        return np.zeros((0, 3))
    face = rng.choice(4, size=n, p=weight / weight.sum())
    along = rng.uniform(-0.5, 0.5, n) * widths[face]
    # Returns come from just inside the skin (wheel arches, bodies, limbs), so an accurate label box
    # contains most of them, as on real data.
    depth_ext = np.where(np.arange(4) < 2, box[3], box[4])[face]
    inset = rng.uniform(0.05, 1.0, n) * np.minimum(0.35, 0.45 * depth_ext)
    xy = centres[face] + tangents[face] * along[:, None] - normals[face] * inset[:, None]
    z = box[2] - box[5] / 2 + rng.uniform(z_frac[0], z_frac[1], n) * box[5]
    return np.concatenate([xy, z[:, None]], 1)


def _expected_points(base: float, box: np.ndarray, cfg: SceneConfig) -> float:
    r = float(np.hypot(box[0], box[1]))
    return base * cfg.points_scale * float(np.clip(10.0 / max(r, 1e-3), 0.35, 2.5))


def _radar(rng: np.random.Generator, cfg: SceneConfig, objects: List[_Item], clutter: List[_Item],
           ego_v: np.ndarray) -> Dict[str, np.ndarray]:
    items = objects + clutter
    all_boxes = np.stack([it.box for it in items]) if items else np.zeros((0, 7))
    pos, vel, rcs, scan, src, owner, item_idx, extra_dop = [], [], [], [], [], [], [], []
    ns = cfg.num_scans

    def add(*columns):
        for store, col in zip((pos, vel, rcs, scan, src, owner, item_idx, extra_dop), columns):
            store.append(col)

    for i, it in enumerate(items):
        if it.is_object:
            sig = _CLASS_RADAR[it.label]
            lam = _expected_points(sig["points"], it.box, cfg) * ns
        else:
            sig = _CLUTTER_RADAR[it.label]
            per = sig["points"] * (it.box[3] if it.label in (3, 4) else 1.0)
            lam = _expected_points(per, it.box, cfg) * ns
        n = int(rng.poisson(lam))
        if it.is_object and it.label == 2:
            # A cyclist's returns come mostly from the rider (a pedestrian-sized sub-box), which makes
            # pedestrians and cyclists look alike to the radar.
            rider = it.box.copy()
            rider[3] = min(0.75, rider[3])
            n_r = int(rng.binomial(n, 0.8))
            p = np.concatenate([_surface_points(rng, rider, n_r, (0.2, 0.98)),
                                _surface_points(rng, it.box, n - n_r, (0.02, 0.45))])
        else:
            z_frac = (0.05, 0.95)
            if not it.is_object and it.label == 0:
                # A pole returns from person height only (like a pedestrian), not from its full length.
                z_frac = (0.03, min(0.95, 1.7 / it.box[5]))
            elif not it.is_object and it.label == 4:
                z_frac = (0.4, 1.0)  # the rail, not the posts
            p = _surface_points(rng, it.box, n, z_frac)
        k = rng.integers(0, ns, len(p))
        # Ego-motion-compensated accumulation: moving objects' older returns trail behind them.
        p[:, :2] -= (k * cfg.scan_period)[:, None] * it.velocity[None]
        micro = cfg.micro_doppler if (it.is_object and it.label in (1, 2) and np.any(it.velocity)) else 0.0
        m = len(p)
        add(p, np.repeat(it.velocity[None], m, 0), it.rcs_mean + rng.normal(0, cfg.rcs_noise, m), k,
            np.full(m, 0 if it.is_object else 2), np.full(m, i if it.is_object else -1), np.full(m, i),
            np.full(m, micro))
        if it.is_object:
            # Multipath ghosts: behind the object along the line of sight, with the object's Doppler.
            g = int(rng.poisson(cfg.ghost_rate * ns))
            if g:
                base = _surface_points(rng, it.box, g)
                gk = rng.integers(0, ns, g)
                base[:, :2] -= (gk * cfg.scan_period)[:, None] * it.velocity[None]
                dist = np.linalg.norm(base, axis=1, keepdims=True)
                gp = base * (1.0 + rng.uniform(0.8, 5.0, (g, 1)) / dist)
                add(gp, np.repeat(it.velocity[None], g, 0), it.rcs_mean - 6 + rng.normal(0, cfg.rcs_noise, g), gk,
                    np.full(g, 1), np.full(g, i), np.full(g, i), np.full(g, micro))

    x0, y0, z0, x1, y1, z1 = cfg.point_cloud_range
    half_fov = math.radians(cfg.radar_fov / 2)
    nn_ = int(rng.poisson(cfg.noise_points * ns))
    r = rng.uniform(max(x0, 1.0), x1, nn_)
    a = rng.uniform(-half_fov, half_fov, nn_)
    noise_p = np.stack([r * np.cos(a), r * np.sin(a), -cfg.radar_height + rng.uniform(0.0, 2.5, nn_)], 1)
    noise_v = np.zeros((nn_, 2))
    outlier = rng.random(nn_) < cfg.noise_doppler_outlier_prob
    # A random radial speed, expressed as a velocity along the line of sight.
    noise_v[outlier] = (rng.uniform(-3, 3, outlier.sum())[:, None] * noise_p[outlier, :2]
                        / np.linalg.norm(noise_p[outlier, :2], axis=1, keepdims=True))
    add(noise_p, noise_v, rng.normal(-6.0, 4.0, nn_), rng.integers(0, ns, nn_), np.full(nn_, 3), np.full(nn_, -1),
        np.full(nn_, -1), np.zeros(nn_))

    p = np.concatenate(pos)
    v = np.concatenate(vel)
    rcs_ = np.concatenate(rcs)
    k = np.concatenate(scan)
    source = np.concatenate(src).astype(np.int64)
    own = np.concatenate(owner).astype(np.int64)
    idx = np.concatenate(item_idx).astype(np.int64)
    micro = np.concatenate(extra_dop)

    # Occlusion: a return hidden behind another item survives only with probability occlusion_leak.
    hits = _segment_hits_boxes(p, all_boxes)
    if hits.size:
        hits[np.arange(len(p))[idx >= 0], idx[idx >= 0]] = False
    # People are thin and not metal: the radar sees past them far more often than past a car or a wall
    # (this is why the paper finds the worst blurring for pedestrians and cyclists, Fig. 1d).
    soft = np.array([it.is_object and it.label in (1, 2) for it in items], dtype=bool)
    hard_hit = hits[:, ~soft].any(1) & (source != 3)
    soft_hit = hits[:, soft].any(1) & (source != 3)
    u = rng.random(len(p))
    keep = np.where(hard_hit, u < cfg.occlusion_leak, np.where(soft_hit, u < cfg.occlusion_leak_people, True))

    # Doppler from the true geometry; ego moves along +x (relative velocity = v - v_ego).
    rng_true = np.linalg.norm(p, axis=1)
    unit = p / np.maximum(rng_true, 1e-9)[:, None]
    v_rc = (v * unit[:, :2]).sum(1) + rng.normal(0, 1, len(p)) * np.sqrt(cfg.doppler_noise ** 2 + micro ** 2)
    v_r = v_rc - (ego_v[None] * unit[:, :2]).sum(1)

    # Spherical measurement noise.
    az = np.arctan2(p[:, 1], p[:, 0]) + rng.normal(0, math.radians(cfg.azimuth_noise), len(p))
    el = np.arcsin(np.clip(p[:, 2] / np.maximum(rng_true, 1e-9), -1, 1)) + rng.normal(
        0, math.radians(cfg.elevation_noise), len(p))
    rr = rng_true + rng.normal(0, cfg.range_noise, len(p))
    meas = np.stack([rr * np.cos(el) * np.cos(az), rr * np.cos(el) * np.sin(az), rr * np.sin(el)], 1)

    in_range = ((meas[:, 0] >= x0) & (meas[:, 0] < x1) & (meas[:, 1] >= y0) & (meas[:, 1] < y1)
                & (meas[:, 2] >= z0) & (meas[:, 2] < z1) & (np.abs(az) <= half_fov))
    keep &= in_range
    pts = np.concatenate([meas, rcs_[:, None], v_r[:, None], v_rc[:, None], (-k)[:, None].astype(np.float64)], 1)  # int negation: t = +0.0, not -0.0
    return dict(points=pts[keep], source=source[keep], owner=own[keep])


# ----------------------------------------------------------------------------------------------------
# Camera
# ----------------------------------------------------------------------------------------------------


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """``(h, w)`` value noise in about ``[-1, 1]``: a coarse random grid, bilinearly upsampled."""
    gh, gw = h // cell + 2, w // cell + 2
    grid = rng.uniform(-1, 1, (gh, gw))
    y = np.arange(h) / cell
    x = np.arange(w) / cell
    y0, x0 = y.astype(int), x.astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None]
    g00, g01 = grid[y0][:, x0], grid[y0][:, x0 + 1]
    g10, g11 = grid[y0 + 1][:, x0], grid[y0 + 1][:, x0 + 1]
    return (g00 * (1 - fx) + g01 * fx) * (1 - fy) + (g10 * (1 - fx) + g11 * fx) * fy


class _Canvas:
    """RGB image with a depth buffer; every primitive writes where it is nearer than what is there."""

    def __init__(self, cfg: SceneConfig, rgb: np.ndarray, texture: np.ndarray) -> None:
        self.h, self.w = cfg.image_size
        self.k = cfg.intrinsics()
        self.s2c = cfg.sensor_to_camera()
        self.camera = np.asarray(cfg.camera_position, dtype=np.float64)
        self.rgb = rgb
        self.texture = texture
        self.depth = np.full((self.h, self.w), np.inf)
        self.ids = np.full((self.h, self.w), -1, dtype=np.int64)
        u = np.arange(self.w, dtype=np.float64)
        v = np.arange(self.h, dtype=np.float64)
        self.ray_x = (u - self.k[0, 2]) / self.k[0, 0]
        self.ray_y = (v - self.k[1, 2]) / self.k[1, 1]

    def to_cam(self, p: np.ndarray) -> np.ndarray:
        return p @ self.s2c[:3, :3].T + self.s2c[:3, 3]

    def project(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        c = self.to_cam(p)
        return c[:, :2] / c[:, 2:3] * self.k[[0, 1], [0, 1]] + self.k[:2, 2], c[:, 2]

    def window(self, uv: np.ndarray):
        l, t = np.floor(uv.min(0)).astype(int)
        r, b = np.ceil(uv.max(0)).astype(int)
        l, t, r, b = max(l, 0), max(t, 0), min(r, self.w - 1), min(b, self.h - 1)
        if l > r or t > b:
            return None
        return slice(t, b + 1), slice(l, r + 1)

    def quad(self, corners: np.ndarray, colour: np.ndarray, item: int, texture_amp: float = 0.05) -> None:
        """Fill a planar convex quad ``(4, 3)`` (sensor frame) with per-pixel depth from its plane."""
        cam = self.to_cam(corners)
        normal = np.cross(cam[1] - cam[0], cam[2] - cam[0])
        offset = normal @ cam[0]
        if abs(offset) < 1e-9:
            return  # seen edge-on
        uv = cam[:, :2] / cam[:, 2:3] * self.k[[0, 1], [0, 1]] + self.k[:2, 2]
        win = self.window(uv)
        if win is None:
            return
        ys, xs = win
        px = np.arange(xs.start, xs.stop, dtype=np.float64)[None]
        py = np.arange(ys.start, ys.stop, dtype=np.float64)[:, None]
        nxt = uv[[1, 2, 3, 0]]
        sign = 1.0 if np.sum(uv[:, 0] * nxt[:, 1] - nxt[:, 0] * uv[:, 1]) >= 0 else -1.0
        inside = np.ones((len(py), px.shape[1]), dtype=bool)
        for (x0, y0), (x1, y1) in zip(uv.tolist(), nxt.tolist()):
            inside &= (((x1 - x0) * sign) * (py - y0) - ((y1 - y0) * sign) * (px - x0)) >= 0
        rx, ry = self.ray_x[xs][None], self.ray_y[ys][:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = offset / (normal[0] * rx + normal[1] * ry + normal[2])
        self._write(win, inside & (z > 0), z, colour, item, texture_amp)

    def sprite(self, win, mask: np.ndarray, colours: np.ndarray, depth: float, item: int, texture_amp=0.05):
        """Paint a flat cut-out at constant ``depth`` (thin objects: people, bicycles)."""
        self._write(win, mask, np.full(mask.shape, depth), colours, item, texture_amp)

    def _write(self, win, mask, z, colour, item, texture_amp):
        front = mask & (z < self.depth[win])
        if not front.any():
            return
        col = np.broadcast_to(np.asarray(colour, dtype=np.float64), front.shape + (3,))
        tex = 1.0 + texture_amp * self.texture[win][..., None]
        region = self.rgb[win]
        region[front] = np.clip(col[front] * tex[front], 0, 1)
        self.depth[win][front] = z[front]
        self.ids[win][front] = item


# Faces of a unit box: (centre, axis-a, axis-b) in local half-extent units; b is "up" on vertical faces.
_FACES = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "back": ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
    "left": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)), "right": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "top": ((0, 0, 1), (1, 0, 0), (0, 1, 0)), "bottom": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
}
_SHADE = {"front": 0.85, "back": 0.8, "left": 0.95, "right": 0.7, "top": 1.1, "bottom": 0.4}


def _face_quad(box: np.ndarray, face: str, a=(-1.0, 1.0), b=(-1.0, 1.0), lift: float = 0.0) -> np.ndarray:
    """``(4, 3)`` sensor-frame corners of the sub-rectangle ``a x b`` (in [-1, 1]) of a box face."""
    c0, ua, ub = (np.asarray(v, dtype=np.float64) for v in _FACES[face])
    half = box[3:6] / 2
    loc = [c0 * half * (1 + lift / np.maximum(half, 1e-9)) + ua * half * aa + ub * half * bb
           for aa, bb in ((a[0], b[0]), (a[1], b[0]), (a[1], b[1]), (a[0], b[1]))]
    loc = np.asarray(loc)
    cy, sy = math.cos(box[6]), math.sin(box[6])
    x = cy * loc[:, 0] - sy * loc[:, 1]
    y = sy * loc[:, 0] + cy * loc[:, 1]
    return np.stack([x, y, loc[:, 2]], 1) + box[:3]


def _facing(box: np.ndarray, face: str, camera: np.ndarray) -> bool:
    """Whether the outward normal of ``face`` points towards the camera (back faces are skipped)."""
    c0 = np.asarray(_FACES[face][0], dtype=np.float64)
    cy, sy = math.cos(box[6]), math.sin(box[6])
    normal = np.array([cy * c0[0] - sy * c0[1], sy * c0[0] + cy * c0[1], c0[2]])
    centre = box[:3] + normal * (np.abs(c0) @ box[3:6]) / 2
    return float(normal @ (centre - camera)) < 0


def _render_box(cv: _Canvas, box: np.ndarray, colour: np.ndarray, item: int, texture_amp: float,
                car: bool, rng: np.random.Generator) -> None:
    faces = [f for f in _FACES if _facing(box, f, cv.camera)]
    for face in faces:
        cv.quad(_face_quad(box, face), colour * _SHADE[face], item, texture_amp)
    if not car:
        return
    glass = np.array([0.12, 0.15, 0.22]) * rng.uniform(0.8, 1.2)
    tyre = np.array([0.05, 0.05, 0.05])
    # Details sit 2 cm in front of their face so the depth test shows them.
    for face in [f for f in ("front", "back") if f in faces]:
        cv.quad(_face_quad(box, face, (-0.8, 0.8), (0.15, 0.8), 0.02), glass, item, 0.02)
        lamp = np.array([1.0, 0.95, 0.75]) if face == "front" else np.array([0.75, 0.02, 0.02])
        for a in ((-0.9, -0.6), (0.6, 0.9)):
            cv.quad(_face_quad(box, face, a, (-0.45, -0.2), 0.02), lamp, item, 0.0)
    for face in [f for f in ("left", "right") if f in faces]:
        cv.quad(_face_quad(box, face, (-0.55, 0.45), (0.15, 0.8), 0.02), glass, item, 0.02)
        for a in ((-0.8, -0.5), (0.5, 0.8)):
            cv.quad(_face_quad(box, face, a, (-1.0, -0.45), 0.02), tyre, item, 0.0)


def _render_person(cv: _Canvas, it: _Item, item: int) -> None:
    """Pedestrian (label 1) or cyclist (label 2) as a flat cut-out at the box centre's depth."""
    box = it.box
    uv, depth = cv.project(box_corners(box)[0])
    win = cv.window(uv)
    if win is None:
        return
    ys, xs = win
    px, py = np.meshgrid(np.arange(xs.start, xs.stop, dtype=np.float64), np.arange(ys.start, ys.stop, dtype=np.float64))
    bottom = box[:3] - np.array([0, 0, box[5] / 2])
    ub, vb = cv.project(bottom[None])[0][0]
    dc = float(cv.to_cam(box[None, :3])[0, 2])  # one depth for the whole cut-out
    sx, sy = cv.k[0, 0] / dc, cv.k[1, 1] / dc  # pixels per metre at the object's depth
    hscale = box[5] / 1.73

    def rect(cx, half_w, h0, h1):  # lateral centre (m), half width (m), heights above ground (m)
        return (np.abs(px - (ub + cx * sx)) <= max(half_w * sx, 0.5)) & (py <= vb - h0 * sy) & (py >= vb - h1 * sy)

    def ellipse(cx, cz, rx, rz):
        return ((px - (ub + cx * sx)) / max(rx * sx, 0.5)) ** 2 + ((py - (vb - cz * sy)) / max(rz * sy, 0.5)) ** 2 <= 1

    colours = np.zeros(px.shape + (3,))
    mask = np.zeros(px.shape, dtype=bool)

    def paint(m, col):
        colours[m] = col
        mask[:] |= m

    cloth, skin = it.colour, it.extra["skin"]
    if it.label == 1:
        paint(rect(-0.09, 0.07, 0.0, 0.85 * hscale) | rect(0.09, 0.07, 0.0, 0.85 * hscale), it.extra["legs"])
        torso = rect(0.0, 0.2, 0.8 * hscale, 1.45 * hscale)
        paint(torso, cloth)
        if it.extra["stripes"][0] > 0:
            stripes = torso & (((vb - py) / sy / 0.12).astype(int) % 2 == 0)
            paint(stripes, cloth * 0.6)
        paint(rect(-0.25, 0.05, 0.85 * hscale, 1.42 * hscale) | rect(0.25, 0.05, 0.85 * hscale, 1.42 * hscale),
              cloth * 0.8)
        paint(ellipse(0.0, 1.58 * hscale, 0.1, 0.12), skin)
    else:
        # Two wheels along the heading; their apparent width shrinks when seen end-on.
        head = np.array([math.cos(box[6]), math.sin(box[6]), 0.0])
        view = box[:3] / np.linalg.norm(box[:3])
        squash = max(abs(float(np.cross(head, view)[2])), 0.25)
        axle = head * 0.55 * box[3] / 1.76
        wheel_uv, _ = cv.project(np.stack([bottom + axle + [0, 0, 0.34], bottom - axle + [0, 0, 0.34]]))
        for wu, wv in wheel_uv:
            d2 = ((px - wu) / max(0.34 * sx * squash, 0.5)) ** 2 + ((py - wv) / max(0.34 * sy, 0.5)) ** 2
            paint((d2 <= 1.0) & (d2 >= 0.55), np.array([0.04, 0.04, 0.04]))
        frame = (np.abs(py - (vb - 0.5 * sy)) <= max(0.05 * sy, 0.5)) & (px >= wheel_uv[:, 0].min()) & (
            px <= wheel_uv[:, 0].max())
        paint(frame, it.extra["legs"])
        paint(rect(0.0, 0.09, 0.45 * hscale, 0.95 * hscale), it.extra["legs"])
        paint(rect(0.0, 0.19, 0.9 * hscale, 1.45 * hscale), cloth)
        paint(ellipse(0.0, 1.57 * hscale, 0.11, 0.12), it.extra["helmet"])
    cv.sprite(win, mask, colours, dc, item, 0.04)


def _background(rng: np.random.Generator, cfg: SceneConfig, cv_k: np.ndarray) -> np.ndarray:
    h, w = cfg.image_size
    v = np.arange(h, dtype=np.float64)[:, None]
    horizon = cv_k[1, 2]  # zero camera pitch: the horizon is the principal row
    tint = rng.normal(0.0, 0.015, 3)
    sky_top, sky_hor = rng.uniform(0.55, 0.75), rng.uniform(0.75, 0.9)
    frac = np.clip(v / max(horizon, 1.0), 0, 1)
    sky = sky_top + (sky_hor - sky_top) * frac
    g_far, g_near = rng.uniform(0.4, 0.55), rng.uniform(0.25, 0.4)
    gfrac = np.clip((v - horizon) / max(h - horizon, 1.0), 0, 1)
    ground = g_far + (g_near - g_far) * gfrac
    base = np.where(v < horizon, sky, ground) * np.ones((1, w))
    base = base + 0.08 * _smooth_noise(rng, h, w, 16) + 0.04 * _smooth_noise(rng, h, w, 4)
    rgb = np.clip(base[..., None] + tint, 0, 1)
    # Distant buildings above the horizon: grey blocks (beyond radar range, so no returns).
    for _ in range(int(rng.integers(3, 8))):
        x0 = int(rng.integers(0, w))
        bw = int(rng.integers(w // 12, w // 4))
        top = int(max(horizon - rng.uniform(0.1, 0.45) * h, 0))
        rgb[top:int(horizon) + 1, x0:x0 + bw] = _grey(rng, 0.35, 0.75)
    return rgb


def _render(rng: np.random.Generator, cfg: SceneConfig, objects: List[_Item], clutter: List[_Item],
            lighting: str) -> Tuple[np.ndarray, np.ndarray]:
    h, w = cfg.image_size
    k = cfg.intrinsics()
    rgb = _background(rng, cfg, k)
    texture = rng.normal(0.0, 1.0, (h, w))
    cv = _Canvas(cfg, rgb, texture)
    for i, it in enumerate(objects):
        if it.label == 0:
            _render_box(cv, it.box, it.colour, i, 0.05, True, rng)
        else:
            _render_person(cv, it, i)
    for j, it in enumerate(clutter):
        _render_box(cv, it.box, it.colour, len(objects) + j, 0.12, False, rng)
    img = cv.rgb
    if lighting == "dark":
        img = img * rng.uniform(*cfg.dark_gain) + rng.normal(0, cfg.dark_noise, img.shape)
    elif lighting == "dazzle":
        # A bright bloom (sun / headlights) washing out part of the image, plus veiling glare.
        cu, cvv = rng.uniform(0.15, 0.85) * w, rng.uniform(0.15, 0.55) * h
        sigma = rng.uniform(0.2, 0.4) * w
        yy, xx = np.mgrid[0:h, 0:w]
        bloom = rng.uniform(0.75, 0.95) * np.exp(-((xx - cu) ** 2 + (yy - cvv) ** 2) / (2 * sigma ** 2))
        img = img + (1 - img) * np.clip(bloom + 0.1, 0, 1)[..., None]
    img = img + rng.normal(0, cfg.image_noise, img.shape)
    return np.clip(img, 0, 1), cv.ids


# ----------------------------------------------------------------------------------------------------
# Public entry points
# ----------------------------------------------------------------------------------------------------


def _boxes_2d(boxes: np.ndarray, lidar2img: np.ndarray, image_size: Tuple[int, int]) -> np.ndarray:
    if len(boxes) == 0:
        return np.zeros((0, 4))
    corners = box_corners(boxes)
    hom = np.concatenate([corners, np.ones(corners.shape[:2] + (1,))], -1) @ lidar2img.T
    uv = hom[..., :2] / hom[..., 2:3]
    h, w = image_size
    lo, hi = uv.min(1), uv.max(1)
    return np.stack([np.clip(lo[:, 0], 0, w - 1), np.clip(lo[:, 1], 0, h - 1),
                     np.clip(hi[:, 0], 0, w - 1), np.clip(hi[:, 1], 0, h - 1)], 1)


def _blurred(points: np.ndarray, boxes: np.ndarray, boxes_2d: np.ndarray, lidar2img: np.ndarray) -> np.ndarray:
    if len(points) == 0 or len(boxes) == 0:
        return np.zeros(len(points), dtype=bool)
    hom = np.concatenate([points[:, :3], np.ones((len(points), 1))], 1) @ lidar2img.T
    d = hom[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = hom[:, :2] / d[:, None]
    in2d = ((uv[:, None, 0] >= boxes_2d[None, :, 0]) & (uv[:, None, 0] <= boxes_2d[None, :, 2])
            & (uv[:, None, 1] >= boxes_2d[None, :, 1]) & (uv[:, None, 1] <= boxes_2d[None, :, 3])).any(1) & (d > 0)
    in3d = np.zeros(len(points), dtype=bool)
    for b in boxes:
        in3d |= points_in_box(points, b)
    return in2d & ~in3d


def generate_scene(seed: int, config: Optional[SceneConfig] = None) -> Scene:
    """One synthetic radar + camera frame, a pure function of ``(seed, config)``.

    Args:
        seed: non-negative int seeding a numpy ``default_rng``.
        config: generator settings (default :class:`SceneConfig()`).

    Returns:
        A :class:`Scene`; ``P`` radar points, ``G`` objects, ``K`` clutter items, image ``(3, H, W)``.

    Example:
        >>> s = generate_scene(0)
        >>> s.points.shape[1], tuple(s.image.shape), s.gt_boxes.shape[1]
        (7, (3, 152, 240), 7)
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise MSSFError(f"seed: expected a non-negative int, got {seed!r}")
    cfg = SceneConfig() if config is None else config
    if not isinstance(cfg, SceneConfig):
        raise MSSFError(f"config: expected a SceneConfig, got {type(cfg).__name__}")
    rng = np.random.default_rng(int(seed))
    objects, clutter = _layout(rng, cfg)
    for it in objects:
        it.extra = dict(skin=_hsv(rng.uniform(0.04, 0.09), rng.uniform(0.3, 0.6), rng.uniform(0.45, 0.95)),
                        legs=_grey(rng, 0.1, 0.35), helmet=_hsv(rng.uniform(0, 1), 0.8, 0.9),
                        stripes=rng.integers(0, 2, 1))
    ego_v = np.zeros(2)
    if rng.random() >= cfg.ego_static_prob:
        ego_v[0] = rng.uniform(*cfg.ego_speed)
    lp = np.asarray(cfg.lighting_probs, dtype=np.float64)
    drawn = LIGHTING_CONDITIONS[int(rng.choice(3, p=lp / lp.sum()))]
    lighting = cfg.lighting or drawn
    radar = _radar(rng, cfg, objects, clutter, ego_v)
    image, ids = _render(rng, cfg, objects, clutter, lighting)

    l2i = cfg.lidar2img()
    gt_boxes = np.stack([it.box for it in objects]) if objects else np.zeros((0, 7))
    cl_boxes = np.stack([it.box for it in clutter]) if clutter else np.zeros((0, 7))
    b2d = _boxes_2d(gt_boxes, l2i, cfg.image_size)
    pts = radar["points"]
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    i64 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.int64))  # noqa: E731
    return Scene(
        points=f32(pts.reshape(-1, 7)),
        image=f32(image.transpose(2, 0, 1)),
        lidar2img=torch.from_numpy(l2i),
        intrinsics=torch.from_numpy(cfg.intrinsics()),
        sensor_to_camera=torch.from_numpy(cfg.sensor_to_camera()),
        gt_boxes=f32(gt_boxes.reshape(-1, 7)),
        gt_labels=i64([it.label for it in objects]),
        gt_boxes_2d=f32(b2d.reshape(-1, 4)),
        gt_velocity=f32(np.stack([it.velocity for it in objects]).reshape(-1, 2) if objects else np.zeros((0, 2))),
        gt_moving=torch.tensor([bool(np.any(it.velocity)) for it in objects], dtype=torch.bool),
        clutter_boxes=f32(cl_boxes.reshape(-1, 7)),
        clutter_kinds=i64([it.label for it in clutter]),
        lighting=lighting,
        blurred_point_mask=torch.from_numpy(_blurred(pts, gt_boxes, b2d, l2i)),
        point_is_clutter=torch.from_numpy(radar["source"] == 2),
        point_source=i64(radar["source"]),
        point_object_index=i64(radar["owner"]),
        instance_map=i64(ids),
        ego_velocity=f32(ego_v),
        seed=int(seed),
    )


def scene_seed(seed: int, split: str, index: int) -> int:
    """The seed of scene ``index`` of ``split``: injective in ``(seed, split, index)``, so splits never share a scene."""
    if split not in _SPLITS:
        raise MSSFError(f"split: expected one of {tuple(_SPLITS)}, got {split!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not (0 <= seed < 2 ** 28):
        raise MSSFError(f"seed: expected an int in [0, 2**28), got {seed!r}")
    if not (0 <= index < 2 ** 32):
        raise MSSFError(f"index: expected an int in [0, 2**32), got {index!r}")
    return (seed << 34) | (_SPLITS[split] << 32) | int(index)


class SyntheticDataset(torch.utils.data.Dataset):
    """``num_scenes`` deterministic scenes of one split; scene ``i`` uses ``scene_seed(seed, split, i)``.

    Args:
        split: ``"train"``, ``"val"`` or ``"test"``.
        num_scenes: dataset length.
        config: generator settings (default :class:`SceneConfig()`).
        seed: base seed shared by the splits of one experiment.
        cache: keep generated scenes in memory (each is ~0.5 MB).

    Example:
        >>> ds = SyntheticDataset("val", 4)
        >>> len(ds), ds.class_names
        (4, ('Car', 'Pedestrian', 'Cyclist'))
    """

    class_names: Tuple[str, ...] = CLASS_NAMES

    def __init__(self, split: str = "train", num_scenes: int = 100, config: Optional[SceneConfig] = None,
                 seed: int = 0, cache: bool = False) -> None:
        scene_seed(seed, split, 0)  # validates split and seed
        if isinstance(num_scenes, bool) or not isinstance(num_scenes, int) or num_scenes < 0:
            raise MSSFError(f"num_scenes: expected a non-negative int, got {num_scenes!r}")
        if config is not None and not isinstance(config, SceneConfig):
            raise MSSFError(f"config: expected a SceneConfig or None, got {type(config).__name__}")
        self.split, self.num_scenes, self.seed = split, num_scenes, seed
        self.config = config or SceneConfig()
        self._cache: Optional[Dict[int, Scene]] = {} if cache else None

    def __len__(self) -> int:
        return self.num_scenes

    def seed_of(self, index: int) -> int:
        """The :func:`generate_scene` seed of scene ``index``."""
        return scene_seed(self.seed, self.split, index)

    def __getitem__(self, index: int) -> Scene:
        if not isinstance(index, (int, np.integer)) or isinstance(index, bool):
            raise MSSFError(f"index: expected an int, got {type(index).__name__}")
        if index < 0:
            index += self.num_scenes
        if not (0 <= index < self.num_scenes):
            raise IndexError(f"index: expected 0 <= index < {self.num_scenes}, got {index}")
        if self._cache is not None and index in self._cache:
            return self._cache[index]
        scene = generate_scene(self.seed_of(int(index)), self.config)
        if self._cache is not None:
            self._cache[int(index)] = scene
        return scene

    @staticmethod
    def collate(scenes: Sequence[Scene]):
        """``DataLoader`` ``collate_fn``: a :class:`mssf_examples.data.RadarCameraBatch`."""
        return Scene.collate(scenes)
