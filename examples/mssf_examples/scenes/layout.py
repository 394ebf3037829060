"""Scene layout of the synthetic scenes: where objects and clutter stand, how they move, their colours."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from .config import _CLASS_RADAR, _CLUTTER_RADAR, CLUTTER_KINDS, SceneConfig
from .geometry import _bev_overlap, _bev_rect, box_corners


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
