"""Tests of the pillar-lift functions against per-row loops."""

from __future__ import annotations

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.geometry import voxel_centroids
from mssf_blocks.functional.lift import (
    bev_shape_for,
    pillar_lift,
    voxelize_points,
    voxels_to_bev,
    voxels_to_bev_sparse,
)
from mssf_blocks.testing import assert_close, gradcheck64


def random_coords(n, b, d, h, w, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.stack([torch.randint(0, b, (n,), generator=g), torch.randint(0, d, (n,), generator=g),
                        torch.randint(0, h, (n,), generator=g), torch.randint(0, w, (n,), generator=g)],
                       dim=1).int()


def _layout(bev, layout):
    """``bev`` in another memory layout with the same values."""
    if layout == "channels_last":
        return bev.contiguous(memory_format=torch.channels_last)
    if layout == "strided":  # no free pixel view: every other column of a twice-as-wide map
        wide = torch.zeros(*bev.shape[:3], 2 * bev.shape[3], dtype=bev.dtype)
        wide[..., ::2] = bev
        return wide[..., ::2]
    return bev


# one image (index_select on a pixel view, or advanced indexing without one) and two (advanced indexing)
@pytest.mark.parametrize("batch", [1, 2])
@pytest.mark.parametrize("layout", ["nchw", "channels_last", "strided"])
@pytest.mark.parametrize("channels", [4, 1])
@pytest.mark.parametrize("stride", [1, 2, (2, 1)])
def test_pillar_lift_matches_loop(stride, channels, layout, batch):
    sy, sx = (stride, stride) if isinstance(stride, int) else stride
    d, h, w = 3, 5, 7  # odd sizes: the last BEV row/column covers a partial cell
    hb, wb = bev_shape_for((h, w), stride)
    assert (hb, wb) == (math.ceil(h / sy), math.ceil(w / sx))
    g = torch.Generator().manual_seed(1)
    bev = torch.randn(batch, channels, hb, wb, generator=g, dtype=torch.float64)
    emb = torch.randn(d, channels, generator=g, dtype=torch.float64)
    coords = random_coords(30, batch, d, h, w)
    src = _layout(bev, layout)
    got = pillar_lift(src, coords, emb, stride)
    exp = torch.stack([bev[b, :, y // sy, x // sx] + emb[z] for b, z, y, x in coords.tolist()])
    assert torch.equal(got, exp) and got.is_contiguous()
    plain = pillar_lift(src, coords, None, stride)
    assert torch.equal(plain, torch.stack([bev[b, :, y // sy, x // sx] for b, z, y, x in coords.tolist()]))
    assert plain.is_contiguous()


@pytest.mark.parametrize("stride", [1, 2])
def test_voxels_to_bev_matches_loop_and_sums_duplicates(stride):
    d, h, w = 2, 4, 6
    hb, wb = bev_shape_for((h, w), stride)
    coords = random_coords(25, 2, d, h, w, seed=3)
    coords = torch.cat([coords, coords[:5]])  # duplicate rows are summed
    feats = torch.randn(30, 3, dtype=torch.float64)
    got = voxels_to_bev(feats, coords, 2, (hb, wb), stride)
    exp = torch.zeros(2, 3, hb, wb, dtype=torch.float64)
    for f, (b, z, y, x) in zip(feats, coords.tolist()):
        exp[b, :, y // stride, x // stride] += f
    assert_close(got, exp)
    # Sparse form: the same sums, one row per occupied pillar, sorted by (b, y, x).
    sf, sc = voxels_to_bev_sparse(feats, coords, 2, (hb, wb), stride)
    assert sc.dtype == torch.int32 and sc.shape[1] == 3
    occupied = sorted({(b, y // stride, x // stride) for b, z, y, x in coords.tolist()})
    assert [tuple(r) for r in sc.tolist()] == occupied
    assert_close(sf, torch.stack([exp[b, :, y, x] for b, y, x in occupied]))


def test_empty_pillars_and_empty_input():
    out = voxels_to_bev(torch.zeros(0, 3), torch.zeros(0, 4, dtype=torch.int32), 2, (3, 4))
    assert out.shape == (2, 3, 3, 4) and float(out.abs().sum()) == 0
    f, c = voxels_to_bev_sparse(torch.zeros(0, 3), torch.zeros(0, 4, dtype=torch.int32), 2, (3, 4))
    assert f.shape == (0, 3) and c.shape == (0, 3)
    lifted = pillar_lift(torch.randn(1, 3, 2, 2), torch.zeros(0, 4, dtype=torch.int32), torch.randn(2, 3))
    assert lifted.shape == (0, 3)
    one = voxels_to_bev(torch.ones(1, 2), torch.tensor([[0, 0, 1, 1]], dtype=torch.int32), 1, (2, 2))
    assert one[0, :, 1, 1].tolist() == [1.0, 1.0] and float(one.sum()) == 2.0


def test_gradcheck_lift_and_sum():
    coords = torch.tensor([[0, 0, 0, 0], [0, 1, 0, 0], [1, 1, 2, 3], [0, 0, 3, 1]], dtype=torch.int32)
    bev = torch.randn(2, 2, 2, 2, dtype=torch.float64)
    emb = torch.randn(2, 2, dtype=torch.float64)
    assert gradcheck64(lambda b, e: pillar_lift(b, coords, e, 2), [bev, emb])
    one = coords.clone()
    one[:, 0] = 0  # one image: the pixel-view path, pillars shared by several voxels
    for layout in ("nchw", "channels_last"):
        b1 = _layout(torch.randn(1, 2, 2, 2, dtype=torch.float64), layout)
        assert gradcheck64(lambda b, e: pillar_lift(b, one, e, 2), [b1, emb])
        assert gradcheck64(lambda b: pillar_lift(b, one, None, 2), [b1])
    feats = torch.randn(4, 2, dtype=torch.float64)
    assert gradcheck64(lambda f: voxels_to_bev(f, coords, 2, (2, 2), 2), [feats])
    assert gradcheck64(lambda f: voxels_to_bev_sparse(f, coords, 2, (2, 2), 2)[0], [feats])


def test_voxelize_points_matches_loop_and_centroid_join():
    g = torch.Generator().manual_seed(4)
    pts = torch.rand(60, 5, generator=g, dtype=torch.float64)
    pts[:, 0] = pts[:, 0] * 2.4 - 0.2  # some points outside x range [0, 2)
    pts[:, 1] = pts[:, 1] * 1.0
    pts[:, 2] = pts[:, 2] * 2.0 - 1.0
    batch = torch.randint(0, 2, (60,), generator=g)
    vs, lo, hi = (0.25, 0.5, 0.5), (0.0, 0.0, -1.0), (2.0, 1.0, 1.0)
    vox = voxelize_points(pts, batch, 2, vs, lo, hi)
    cnt = voxelize_points(pts, batch, 2, vs, lo, hi, features="count")
    assert vox.spatial_shape == (4, 2, 8)
    groups = {}
    for p, b in zip(pts.tolist(), batch.tolist()):
        if not (0 <= p[0] < 2 and 0 <= p[1] < 1 and -1 <= p[2] < 1):
            continue
        key = (b, math.floor((p[2] + 1) / 0.5), math.floor(p[1] / 0.5), math.floor(p[0] / 0.25))
        groups.setdefault(key, []).append(p)
    keys = sorted(groups)
    assert [tuple(r) for r in vox.coords.tolist()] == keys
    assert torch.equal(vox.coords, cnt.coords)
    exp = torch.tensor([[sum(col) / len(groups[k]) for col in zip(*groups[k])] for k in keys],
                       dtype=torch.float64)
    assert_close(vox.features, exp)
    assert cnt.features.flatten().tolist() == [float(len(groups[k])) for k in keys]
    # Every voxel holds its points: the centroid join finds them all.
    cen, has = voxel_centroids(pts, batch, vox.coords, vox.spatial_shape, 2, vs, lo, point_range_max=hi)
    assert bool(has.all())
    assert_close(cen, vox.features[:, :3])


def test_voxelize_points_empty():
    vox = voxelize_points(torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), 1, (1.0, 1.0, 1.0),
                          (0.0, 0.0, 0.0), (2.0, 2.0, 1.0))
    assert vox.coords.shape == (0, 4) and vox.features.shape == (0, 4)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: pillar_lift(torch.zeros(1, 2, 2, 2), torch.tensor([[0, 0, 4, 0]], dtype=torch.int32)),
         r"coords\[:, 2\]"),
        (lambda: pillar_lift(torch.zeros(1, 2, 2, 2), torch.tensor([[1, 0, 0, 0]], dtype=torch.int32)),
         r"coords\[:, 0\]"),
        (lambda: pillar_lift(torch.zeros(1, 2, 2, 2), torch.tensor([[0, 0, 0, 0]], dtype=torch.float32)),
         "coords"),
        (lambda: pillar_lift(torch.zeros(1, 2, 2, 2), torch.tensor([[0, 2, 0, 0]]), torch.zeros(2, 2)),
         r"coords\[:, 1\]"),
        (lambda: pillar_lift(torch.zeros(1, 2, 2, 2), torch.tensor([[0, 0, 0, 0]]), torch.zeros(2, 3)),
         "height_embedding"),
        (lambda: pillar_lift(torch.zeros(2, 2, 2), torch.tensor([[0, 0, 0, 0]])), "bev"),
        (lambda: pillar_lift(torch.zeros(1, 2, 2, 2), torch.tensor([[0, 0, 0, 0]]), stride=0), "stride"),
        (lambda: voxels_to_bev(torch.zeros(2, 2), torch.zeros(3, 4, dtype=torch.int32), 1, (2, 2)), "coords"),
        (lambda: voxels_to_bev(torch.zeros(1, 2), torch.tensor([[0, 0, 0, 5]]), 1, (2, 2)), r"coords\[:, 3\]"),
        (lambda: voxels_to_bev(torch.zeros(1, 2), torch.tensor([[0, 0, 0, 0]]), 1, (2,)), "bev_shape"),
        (lambda: voxels_to_bev(torch.zeros(1, 2), torch.tensor([[0, 0, 0, 0]]), 0, (2, 2)), "batch_size"),
        (lambda: voxels_to_bev(torch.zeros(1, 2), torch.tensor([[0, 0, -1, 0]]), 1, (2, 2)), "coords"),
        (lambda: voxelize_points(torch.zeros(2, 3), torch.zeros(2, dtype=torch.long), 1, (0.3, 1, 1),
                                 (0, 0, 0), (1, 1, 1)), "point_range_max"),
        (lambda: voxelize_points(torch.zeros(2, 3), torch.zeros(2, dtype=torch.long), 1, (1, 1, 1),
                                 (0, 0, 0), (1, 1, 1), features="max"), "features"),
        (lambda: voxelize_points(torch.zeros(2, 3), torch.ones(2, dtype=torch.long), 1, (1, 1, 1),
                                 (0, 0, 0), (1, 1, 1)), "points_batch"),
        (lambda: voxelize_points(torch.zeros(2, 2), torch.zeros(2, dtype=torch.long), 1, (1, 1, 1),
                                 (0, 0, 0), (1, 1, 1)), "points"),
    ],
)
def test_bad_input(call, match):
    with pytest.raises(MSSFError, match=match):
        call()
