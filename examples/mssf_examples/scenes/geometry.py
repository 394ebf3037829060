"""Box geometry of the synthetic scenes (numpy, float64): corners, point-in-box, BEV overlap, occlusion rays."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["box_corners", "points_in_box"]


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
