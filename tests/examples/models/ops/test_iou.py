"""Tests for ``mssf_examples.models.ops.iou`` against shapely polygons (an independent reference)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

shapely = pytest.importorskip("shapely")
from shapely.geometry import Polygon  # noqa: E402

from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_examples.models.ops.iou import (  # noqa: E402
    box_corners_bev,
    box_intersection_bev,
    box_iou_3d,
    box_iou_bev,
    box_iou_bev_3d,
)

TOL = 1e-6


def _polygon(box) -> Polygon:
    """Rectangle from (x, y, dx, dy, yaw) with numpy trigonometry (not the code under test)."""
    x, y, _, dx, dy, _, yaw = (float(v) for v in box)
    c, s = math.cos(yaw), math.sin(yaw)
    pts = []
    for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
        lx, ly = sx * dx / 2, sy * dy / 2
        pts.append((x + c * lx - s * ly, y + s * lx + c * ly))
    return Polygon(pts)


def _reference(a: torch.Tensor, b: torch.Tensor):
    """(intersection area, BEV IoU, 3D IoU) matrices by shapely, pair by pair."""
    n, m = a.shape[0], b.shape[0]
    inter = np.zeros((n, m))
    iou_bev = np.zeros((n, m))
    iou_3d = np.zeros((n, m))
    for i in range(n):
        pa = _polygon(a[i])
        for j in range(m):
            pb = _polygon(b[j])
            area = pa.intersection(pb).area
            inter[i, j] = area
            union = pa.area + pb.area - area
            iou_bev[i, j] = area / union if union > 0 else 0.0
            za, zb = float(a[i, 2]), float(b[j, 2])
            ha, hb = float(a[i, 5]), float(b[j, 5])
            h = max(0.0, min(za + ha / 2, zb + hb / 2) - max(za - ha / 2, zb - hb / 2))
            vol = area * h
            union3 = pa.area * ha + pb.area * hb - vol
            iou_3d[i, j] = vol / union3 if union3 > 0 else 0.0
    return (torch.from_numpy(inter), torch.from_numpy(iou_bev), torch.from_numpy(iou_3d))


def _random_boxes(n: int, gen: torch.Generator, spread: float = 3.0) -> torch.Tensor:
    xyz = (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5) * 2 * spread
    size = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 3.0 + 0.2
    yaw = (torch.rand(n, 1, generator=gen, dtype=torch.float64) - 0.5) * 4 * math.pi  # beyond [-pi, pi]
    return torch.cat([xyz, size, yaw], dim=1)


def _box(x, y, dx, dy, yaw, z=0.0, dz=1.0):
    return [x, y, z, dx, dy, dz, yaw]


def _check_against_shapely(a, b):
    inter_ref, bev_ref, iou3d_ref = _reference(a, b)
    torch.testing.assert_close(box_intersection_bev(a, b), inter_ref, rtol=0, atol=TOL)
    torch.testing.assert_close(box_iou_bev(a, b), bev_ref, rtol=0, atol=TOL)
    torch.testing.assert_close(box_iou_3d(a, b), iou3d_ref, rtol=0, atol=TOL)
    both_bev, both_3d = box_iou_bev_3d(a, b)
    torch.testing.assert_close(both_bev, bev_ref, rtol=0, atol=TOL)
    torch.testing.assert_close(both_3d, iou3d_ref, rtol=0, atol=TOL)


def test_corners_are_counter_clockwise_and_match_reference():
    boxes = torch.tensor([_box(1.0, 2.0, 4.0, 2.0, 0.3)], dtype=torch.float64)
    corners = box_corners_bev(boxes)[0]
    ref = np.asarray(_polygon(boxes[0]).exterior.coords)[:4]
    torch.testing.assert_close(corners, torch.from_numpy(ref), rtol=0, atol=1e-12)
    # Shoelace > 0 means counter-clockwise.
    x, y = corners[:, 0], corners[:, 1]
    assert float((x * y.roll(-1) - x.roll(-1) * y).sum()) > 0


def test_random_boxes_match_shapely():
    gen = torch.Generator().manual_seed(0)
    a = _random_boxes(40, gen)
    b = _random_boxes(35, gen)
    _check_against_shapely(a, b)
    # Make sure the random set actually exercises partial overlaps, not only zeros.
    iou = box_iou_bev(a, b)
    assert int(((iou > 0.05) & (iou < 0.95)).sum()) > 50


def _clip_area(poly_a, poly_b) -> float:
    """Sutherland-Hodgman clipping of convex ``poly_a`` by convex ``poly_b`` (both CCW), plain Python.

    A second reference for exactly degenerate configurations (shared edge lines), where GEOS
    occasionally returns an empty intersection for boxes that fully overlap.
    """
    out = list(poly_a)
    for k in range(len(poly_b)):
        (x1, y1), (x2, y2) = poly_b[k], poly_b[(k + 1) % len(poly_b)]
        scale = math.hypot(x2 - x1, y2 - y1)

        def side(p):
            return ((x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1)) / scale

        inp, out = out, []
        for i in range(len(inp)):
            p, q = inp[i], inp[(i + 1) % len(inp)]
            sp, sq = side(p), side(q)
            if sp >= -1e-12:
                out.append(p)
            if (sp > 1e-12 and sq < -1e-12) or (sp < -1e-12 and sq > 1e-12):
                t = sp / (sp - sq)
                out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
        if not out:
            return 0.0
    return 0.5 * abs(sum(out[i][0] * out[(i + 1) % len(out)][1] - out[(i + 1) % len(out)][0] * out[i][1]
                         for i in range(len(out))))


def test_lattice_boxes_match_clipping_reference():
    # Centres on a 0.5 m lattice, sizes 1 or 2, yaw multiples of 45 degrees: many shared edge lines,
    # coincident corners, containment and exact touching.
    gen = torch.Generator().manual_seed(5)
    n = 120
    xy = torch.randint(-2, 3, (n, 2), generator=gen).double() * 0.5
    size = torch.randint(1, 3, (n, 2), generator=gen).double()
    yaw = torch.randint(-8, 9, (n, 1), generator=gen).double() * math.pi / 4
    boxes = torch.cat([xy, torch.zeros(n, 1, dtype=torch.float64), size,
                       torch.ones(n, 1, dtype=torch.float64), yaw], dim=1)
    a, b = boxes[:30], boxes
    polys_a = [list(_polygon(x).exterior.coords)[:4] for x in a]
    polys_b = [list(_polygon(x).exterior.coords)[:4] for x in b]
    ref = torch.tensor([[_clip_area(pa, pb) for pb in polys_b] for pa in polys_a], dtype=torch.float64)
    torch.testing.assert_close(box_intersection_bev(a, b), ref, rtol=0, atol=TOL)


def test_small_chunks_give_the_same_result():
    gen = torch.Generator().manual_seed(1)
    a = _random_boxes(20, gen)
    b = _random_boxes(15, gen)
    _, ref, _ = _reference(a, b)
    torch.testing.assert_close(box_iou_bev(a, b, chunk_size=7), ref, rtol=0, atol=TOL)


@pytest.mark.parametrize(
    "box_a, box_b, expected_bev",
    [
        # identical boxes
        (_box(1.0, -2.0, 4.0, 2.0, 0.7), _box(1.0, -2.0, 4.0, 2.0, 0.7), 1.0),
        # same box, yaw differing by pi and 2 pi (yaw wrap): same rectangle
        (_box(0.0, 0.0, 4.0, 2.0, 0.2), _box(0.0, 0.0, 4.0, 2.0, 0.2 + math.pi), 1.0),
        (_box(0.0, 0.0, 4.0, 2.0, -3.0), _box(0.0, 0.0, 4.0, 2.0, -3.0 + 2 * math.pi), 1.0),
        # same centre rotated 90 degrees: 2x2 overlap, union 8 + 8 - 4
        (_box(0.0, 0.0, 4.0, 2.0, 0.0), _box(0.0, 0.0, 4.0, 2.0, math.pi / 2), 4.0 / 12.0),
        # square rotated 45 degrees against itself (regular octagon overlap)
        (_box(0.0, 0.0, 2.0, 2.0, 0.0), _box(0.0, 0.0, 2.0, 2.0, math.pi / 4), None),
        # touching edges: zero overlap
        (_box(0.0, 0.0, 2.0, 2.0, 0.0), _box(2.0, 0.0, 2.0, 2.0, 0.0), 0.0),
        # touching corners only
        (_box(0.0, 0.0, 2.0, 2.0, 0.0), _box(2.0, 2.0, 2.0, 2.0, 0.0), 0.0),
        # one inside the other (axis-aligned and rotated)
        (_box(0.0, 0.0, 4.0, 4.0, 0.0), _box(0.5, 0.5, 1.0, 1.0, 0.0), 1.0 / 16.0),
        (_box(0.0, 0.0, 4.0, 4.0, 0.3), _box(0.2, -0.1, 1.0, 2.0, 1.1), 2.0 / 16.0),
        # inner box sharing an edge with the outer one
        (_box(0.0, 0.0, 4.0, 4.0, 0.0), _box(1.5, 0.0, 1.0, 4.0, 0.0), 4.0 / 16.0),
        # half overlap along x
        (_box(0.0, 0.0, 2.0, 2.0, 0.0), _box(1.0, 0.0, 2.0, 2.0, 0.0), 2.0 / 6.0),
        # far apart
        (_box(0.0, 0.0, 2.0, 2.0, 0.0), _box(10.0, 0.0, 2.0, 2.0, 0.4), 0.0),
        # cross shape: thin boxes crossing at 90 degrees (no corner inside the other)
        (_box(0.0, 0.0, 6.0, 1.0, 0.0), _box(0.0, 0.0, 6.0, 1.0, math.pi / 2), 1.0 / 11.0),
        # large coordinates
        (_box(1e4, -5e3, 4.0, 2.0, 0.1), _box(1e4 + 0.5, -5e3, 4.0, 2.0, 0.1), None),
    ],
)
def test_degenerate_cases(box_a, box_b, expected_bev):
    a = torch.tensor([box_a], dtype=torch.float64)
    b = torch.tensor([box_b], dtype=torch.float64)
    _check_against_shapely(a, b)
    _check_against_shapely(b, a)
    if expected_bev is not None:
        assert abs(float(box_iou_bev(a, b)) - expected_bev) < TOL


def test_iou_3d_z_overlap_by_hand():
    # Identical BEV footprints (2 x 2), heights [0, 2] and [1, 3]: overlap 4 * 1, union 8 + 8 - 4.
    a = torch.tensor([[0.0, 0.0, 1.0, 2.0, 2.0, 2.0, 0.0]], dtype=torch.float64)
    b = torch.tensor([[0.0, 0.0, 2.0, 2.0, 2.0, 2.0, 0.0]], dtype=torch.float64)
    assert abs(float(box_iou_3d(a, b)) - 4.0 / 12.0) < 1e-12
    # Disjoint in z: zero 3D IoU although the BEV IoU is 1.
    c = torch.tensor([[0.0, 0.0, 5.0, 2.0, 2.0, 2.0, 0.0]], dtype=torch.float64)
    assert float(box_iou_3d(a, c)) == 0.0
    assert abs(float(box_iou_bev(a, c)) - 1.0) < 1e-12


def test_float32_input_returns_float32_close_to_reference():
    gen = torch.Generator().manual_seed(2)
    a = _random_boxes(10, gen)
    b = _random_boxes(12, gen)
    _, ref, _ = _reference(a, b)
    out = box_iou_bev(a.float(), b.float())
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), ref, rtol=0, atol=1e-5)


def test_empty_and_zero_size():
    a = torch.zeros(0, 7, dtype=torch.float64)
    b = torch.tensor([_box(0.0, 0.0, 1.0, 1.0, 0.0)], dtype=torch.float64)
    assert box_iou_bev(a, b).shape == (0, 1)
    assert box_iou_3d(b, a).shape == (1, 0)
    flat = torch.tensor([_box(0.0, 0.0, 0.0, 0.0, 0.0)], dtype=torch.float64)
    out = box_iou_bev(flat, flat)
    assert torch.isfinite(out).all() and float(out) == 0.0


def test_many_boxes_memory_bounded():
    # 1000 x 1000 boxes in a 100 m scene: only nearby pairs are computed; spot-check a few rows.
    gen = torch.Generator().manual_seed(3)
    a = _random_boxes(1000, gen, spread=50.0)
    iou = box_iou_bev(a, a)
    assert iou.shape == (1000, 1000)
    torch.testing.assert_close(torch.diagonal(iou), torch.ones(1000, dtype=torch.float64), rtol=0, atol=TOL)
    _, ref, _ = _reference(a[:5], a)
    torch.testing.assert_close(iou[:5], ref, rtol=0, atol=TOL)


def test_gradient_flows():
    a = torch.tensor([_box(0.0, 0.0, 2.0, 2.0, 0.1)], dtype=torch.float64, requires_grad=True)
    b = torch.tensor([_box(0.7, 0.3, 2.0, 1.5, 0.5)], dtype=torch.float64)
    iou = box_iou_bev(a, b)
    iou.sum().backward()
    assert torch.isfinite(a.grad).all() and float(a.grad.abs().sum()) > 0
    assert torch.autograd.gradcheck(lambda x: box_intersection_bev(x, b), (a,), eps=1e-6, atol=1e-6)


def test_bad_input_raises():
    good = torch.zeros(2, 7)
    with pytest.raises(MSSFError, match="a"):
        box_iou_bev(torch.zeros(2, 6), good)
    with pytest.raises(MSSFError, match="b"):
        box_iou_bev(good, torch.zeros(2, 7, dtype=torch.long))
    neg = torch.tensor([[0.0, 0.0, 0.0, -1.0, 1.0, 1.0, 0.0]])
    with pytest.raises(MSSFError, match="non-negative"):
        box_iou_3d(neg, good)
    with pytest.raises(MSSFError, match="finite"):
        box_iou_bev(torch.full((1, 7), float("nan")), good)
    with pytest.raises(MSSFError, match="chunk_size"):
        box_iou_bev(good, good, chunk_size=0)
