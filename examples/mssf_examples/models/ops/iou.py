"""Rotated box overlaps: bird's-eye-view (BEV) and 3D intersection-over-union.

Boxes are ``(x, y, z, dx, dy, dz, yaw)`` in the sensor frame: ``z`` is the box centre, ``yaw`` turns
about +z and ``dx`` lies along the heading (the library-wide convention).

The BEV intersection of two rectangles is a convex polygon whose vertices are (a) the corners of each
rectangle that lie inside the other and (b) the crossings of their edges. For every box pair we
collect those 4 + 4 + 16 = 24 candidate points with a validity mask, sort the valid ones by angle
about their mean and take the shoelace area -- all as batched tensor operations, no Python loop over
pairs. The 3D IoU multiplies the BEV intersection area by the overlap of the ``z`` extents (the
KITTI / OpenPCDet definition for boxes that only turn about the vertical axis).

Numerics:

* The geometry is computed in float64 whatever the input dtype (the result is cast back), each pair
  in coordinates relative to the first box's centre, so that IoU values near a threshold (NMS,
  evaluation) do not flip with float32 rounding of large coordinates.
* Corner-inside tests and edge-crossing parameters accept a relative slack of ``1e-9``: for identical,
  touching or collinear-edge boxes the corners sitting on the other box's boundary then count, and the
  duplicates this creates add zero area.
* Only pairs whose circumscribed circles meet are computed, in chunks of at most ``chunk_size`` pairs,
  so memory stays bounded for ``N, M ~ 1000`` (the dense ``(N, M)`` output itself is the only
  ``O(N M)`` allocation).
"""

from __future__ import annotations

from typing import Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_finite, check_floating, check_shape
from mssf_blocks.errors import MSSFError

__all__ = [
    "box_corners_bev",
    "box_intersection_bev",
    "box_iou_bev",
    "box_iou_3d",
    "box_iou_bev_3d",
    "DEFAULT_CHUNK_SIZE",
]

#: Maximum number of box pairs processed at once (each pair needs roughly 2 kB of temporaries).
DEFAULT_CHUNK_SIZE = 32768

# Relative slack for boundary tests (see the module docstring).
_REL_EPS = 1e-9


def _check_boxes(a: Tensor, b: Tensor) -> None:
    check_shape(a, "a", (None, 7))
    check_shape(b, "b", (None, 7))
    for x, name in ((a, "a"), (b, "b")):
        check_floating(x, name)
        check_finite(x, name)
        if x.numel() and bool((x[:, 3:6] < 0).any()):
            raise MSSFError(f"{name}: expected non-negative box sizes (dx, dy, dz) in columns 3:6, "
                            f"got a minimum of {float(x[:, 3:6].min())}")
    if a.device != b.device:
        raise MSSFError(f"a and b: expected tensors on the same device, got {a.device} and {b.device}")


def box_corners_bev(boxes: Tensor) -> Tensor:
    """BEV corners of rotated boxes, counter-clockwise.

    Args:
        boxes: ``(N, 7)`` boxes ``(x, y, z, dx, dy, dz, yaw)`` (only ``x, y, dx, dy, yaw`` are used).

    Returns:
        ``(N, 4, 2)`` corners ``(x, y)``: front-left, rear-left, rear-right, front-right in the box's own
        frame (counter-clockwise seen from +z).
    """
    signs = boxes.new_tensor([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
    local = signs * (0.5 * boxes[:, None, 3:5])  # (N, 4, 2)
    cos, sin = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]
    x = local[..., 0] * cos - local[..., 1] * sin + boxes[:, None, 0]
    y = local[..., 0] * sin + local[..., 1] * cos + boxes[:, None, 1]
    return torch.stack([x, y], dim=-1)


def _cross(u: Tensor, v: Tensor) -> Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _inside(points: Tensor, boxes: Tensor) -> Tensor:
    """``points (P, K, 2)`` inside (with slack) the rectangle ``boxes (P, 7)``; returns ``(P, K)`` bool."""
    d = points - boxes[:, None, 0:2]
    cos, sin = torch.cos(boxes[:, 6])[:, None], torch.sin(boxes[:, 6])[:, None]
    lx = d[..., 0] * cos + d[..., 1] * sin
    ly = -d[..., 0] * sin + d[..., 1] * cos
    half = 0.5 * boxes[:, 3:5]
    slack = _REL_EPS * (1.0 + half.amax(dim=1, keepdim=True))
    return (lx.abs() <= half[:, 0:1] + slack) & (ly.abs() <= half[:, 1:2] + slack)


def _pair_intersection(a: Tensor, b: Tensor) -> Tensor:
    """BEV intersection areas of paired boxes ``a, b (P, 7)`` (float64, ``a``'s centre at the origin)."""
    ca, cb = box_corners_bev(a), box_corners_bev(b)  # (P, 4, 2)

    # (a) corners inside the other box.
    a_in_b = _inside(ca, b)
    b_in_a = _inside(cb, a)

    # (b) edge crossings: edge i of a is p + t r, edge j of b is q + u s, t, u in [0, 1].
    p = ca[:, :, None, :]  # (P, 4, 1, 2)
    r = (ca.roll(-1, dims=1) - ca)[:, :, None, :]
    q = cb[:, None, :, :]  # (P, 1, 4, 2)
    s = (cb.roll(-1, dims=1) - cb)[:, None, :, :]
    denom = _cross(r, s)  # (P, 4, 4)
    qp = q - p
    scale = r.norm(dim=-1) * s.norm(dim=-1)
    # Parallel (or degenerate) edges never contribute a crossing: their shared stretch, if any, ends
    # at corners that the inside tests above already collect.
    parallel = denom.abs() <= _REL_EPS * scale
    safe = torch.where(parallel, torch.ones_like(denom), denom)
    t = _cross(qp, s) / safe
    u = _cross(qp, r) / safe
    lo, hi = -_REL_EPS, 1.0 + _REL_EPS
    crossing = ~parallel & (t >= lo) & (t <= hi) & (u >= lo) & (u <= hi)
    points_x = (p + t[..., None] * r).flatten(1, 2)  # (P, 16, 2)

    points = torch.cat([ca, cb, points_x], dim=1)  # (P, 24, 2)
    valid = torch.cat([a_in_b, b_in_a, crossing.flatten(1, 2)], dim=1)  # (P, 24)

    count = valid.sum(dim=1)
    w = valid.to(points.dtype)[..., None]
    centre = (points * w).sum(dim=1) / count.clamp_min(1)[:, None].to(points.dtype)
    rel = points - centre[:, None, :]
    angle = torch.atan2(rel[..., 1], rel[..., 0])
    # Invalid points sort last (atan2 is within [-pi, pi]).
    angle = torch.where(valid, angle, torch.full_like(angle, 10.0))
    order = angle.argsort(dim=1)
    rel = torch.gather(rel, 1, order[..., None].expand(-1, -1, 2))
    valid_sorted = torch.gather(valid, 1, order)
    # Replacing the trailing invalid points by the first valid one closes the polygon: the last valid
    # point connects to it and the repeated copies add zero area.
    rel = torch.where(valid_sorted[..., None], rel, rel[:, 0:1, :].expand_as(rel))
    area = 0.5 * _cross(rel, rel.roll(-1, dims=1)).sum(dim=1)
    area = torch.where(count >= 3, area, torch.zeros_like(area))
    # Numerical guard only: rounding can push a true 0 (touching boxes) or a full containment a few
    # ulps outside [0, min area].
    max_area = torch.minimum(a[:, 3] * a[:, 4], b[:, 3] * b[:, 4])
    return torch.minimum(area.clamp_min(0.0), max_area)


def box_intersection_bev(a: Tensor, b: Tensor, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Tensor:
    """Area of the BEV intersection of every pair of rotated boxes.

    Args:
        a: ``(N, 7)`` boxes ``(x, y, z, dx, dy, dz, yaw)``.
        b: ``(M, 7)`` boxes.
        chunk_size: maximum number of overlapping-candidate pairs processed at once (memory bound).

    Returns:
        ``(N, M)`` intersection areas in ``a``'s dtype (computed in float64).
    """
    _check_boxes(a, b)
    if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size <= 0:
        raise MSSFError(f"chunk_size: expected a positive int, got {chunk_size!r}")
    out_dtype = torch.promote_types(a.dtype, b.dtype)
    n, m = a.shape[0], b.shape[0]
    a64, b64 = a.to(torch.float64), b.to(torch.float64)
    out = torch.zeros(n, m, dtype=torch.float64, device=a.device)
    if n == 0 or m == 0:
        return out.to(out_dtype)

    # Only pairs whose circumscribed circles meet can overlap.
    radius_a = 0.5 * torch.hypot(a64[:, 3], a64[:, 4])
    radius_b = 0.5 * torch.hypot(b64[:, 3], b64[:, 4])
    dist = torch.cdist(a64[:, 0:2], b64[:, 0:2])
    reach = radius_a[:, None] + radius_b[None, :]
    ia, ib = torch.nonzero(dist <= reach * (1.0 + 1e-6) + 1e-9, as_tuple=True)

    areas = []
    for start in range(0, ia.numel(), chunk_size):
        pa = a64[ia[start:start + chunk_size]]
        pb = b64[ib[start:start + chunk_size]]
        # Work relative to a's centre: small coordinates keep the cross products accurate.
        origin = torch.zeros_like(pa)
        origin[:, 0:2] = pa[:, 0:2]
        areas.append(_pair_intersection(pa - origin, pb - origin))
    if areas:
        out = out.index_put((ia, ib), torch.cat(areas))
    return out.to(out_dtype)


def _ratio(inter: Tensor, union: Tensor) -> Tensor:
    # Two empty (zero-area) boxes have union 0: report IoU 0 rather than NaN.
    positive = union > 0
    return torch.where(positive, inter / torch.where(positive, union, torch.ones_like(union)),
                       torch.zeros_like(inter))


def _ious(a: Tensor, b: Tensor, chunk_size: int, bev: bool, three_d: bool):
    inter_bev = box_intersection_bev(a, b, chunk_size).to(torch.float64)
    a64, b64 = a.to(torch.float64), b.to(torch.float64)
    out_dtype = torch.promote_types(a.dtype, b.dtype)
    iou_bev = iou_3d = None
    if bev:
        area_a = a64[:, 3] * a64[:, 4]
        area_b = b64[:, 3] * b64[:, 4]
        iou_bev = _ratio(inter_bev, area_a[:, None] + area_b[None, :] - inter_bev).to(out_dtype)
    if three_d:
        top = torch.minimum(a64[:, None, 2] + 0.5 * a64[:, None, 5], b64[None, :, 2] + 0.5 * b64[None, :, 5])
        bottom = torch.maximum(a64[:, None, 2] - 0.5 * a64[:, None, 5], b64[None, :, 2] - 0.5 * b64[None, :, 5])
        inter = inter_bev * (top - bottom).clamp_min(0.0)
        vol_a = a64[:, 3] * a64[:, 4] * a64[:, 5]
        vol_b = b64[:, 3] * b64[:, 4] * b64[:, 5]
        iou_3d = _ratio(inter, vol_a[:, None] + vol_b[None, :] - inter).to(out_dtype)
    return iou_bev, iou_3d


def box_iou_bev(a: Tensor, b: Tensor, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Tensor:
    """Rotated bird's-eye-view IoU of every pair of boxes.

    Args:
        a: ``(N, 7)`` boxes ``(x, y, z, dx, dy, dz, yaw)`` (``z, dz`` ignored).
        b: ``(M, 7)`` boxes.
        chunk_size: maximum number of candidate pairs processed at once.

    Returns:
        ``(N, M)`` IoU in ``[0, 1]``, dtype of the inputs (computed in float64). Pairs of zero-area
        boxes get 0.

    Example:
        >>> box = torch.tensor([[0.0, 0.0, 0.0, 2.0, 1.0, 1.0, 0.0]])
        >>> turned = torch.tensor([[0.0, 0.0, 0.0, 2.0, 1.0, 1.0, 1.5707963267948966]])
        >>> round(float(box_iou_bev(box, turned)), 6)  # 1x1 overlap of two 2x1 boxes
        0.333333
    """
    return _ious(a, b, chunk_size, bev=True, three_d=False)[0]


def box_iou_3d(a: Tensor, b: Tensor, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Tensor:
    """Rotated 3D IoU (yaw about +z only) of every pair of boxes.

    ``IoU = A_bev_inter * h_overlap / (V_a + V_b - A_bev_inter * h_overlap)`` with ``h_overlap`` the
    overlap of the intervals ``[z - dz/2, z + dz/2]`` (``z`` is the box centre).

    Args:
        a: ``(N, 7)`` boxes ``(x, y, z, dx, dy, dz, yaw)``.
        b: ``(M, 7)`` boxes.
        chunk_size: maximum number of candidate pairs processed at once.

    Returns:
        ``(N, M)`` IoU in ``[0, 1]``, dtype of the inputs (computed in float64). Pairs of zero-volume
        boxes get 0.
    """
    return _ious(a, b, chunk_size, bev=False, three_d=True)[1]


def box_iou_bev_3d(a: Tensor, b: Tensor, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Tuple[Tensor, Tensor]:
    """``(box_iou_bev(a, b), box_iou_3d(a, b))`` from one shared BEV intersection (half the work).

    Args:
        a: ``(N, 7)`` boxes.
        b: ``(M, 7)`` boxes.
        chunk_size: maximum number of candidate pairs processed at once.

    Returns:
        ``(N, M)`` BEV IoU and ``(N, M)`` 3D IoU.
    """
    return _ious(a, b, chunk_size, bev=True, three_d=True)
