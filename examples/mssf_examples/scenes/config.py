"""Settings and fixed world parameters of the synthetic scenes (:mod:`mssf_examples.scenes.synthetic`).

The class / clutter / lighting / point-source names, the per-class and per-clutter radar signatures the
layout and the radar simulation draw from, and :class:`SceneConfig`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np

from mssf_blocks.errors import MSSFError

__all__ = ["CLASS_NAMES", "CLUTTER_KINDS", "LIGHTING_CONDITIONS", "POINT_SOURCES", "SceneConfig"]

#: Object classes, indexed by ``Scene.gt_labels``.
CLASS_NAMES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
#: Clutter kinds, indexed by ``Scene.clutter_kinds``.
CLUTTER_KINDS: Tuple[str, ...] = ("pole", "car_like", "small_box", "wall", "guard_rail")
#: Lighting conditions, the values of ``Scene.lighting``.
LIGHTING_CONDITIONS: Tuple[str, ...] = ("normal", "dark", "dazzle")
#: Codes of ``Scene.point_source``.
POINT_SOURCES: Tuple[str, ...] = ("object", "ghost", "clutter", "noise")


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
