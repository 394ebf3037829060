"""Pure functions of the pillar version (paper Sec. III-G, "Extend to Pillar").

A pillar network keeps 2D BEV features. To fuse image features into it, the raw points are voxelised
with the BEV grid's x/y resolution and some z resolution, every non-empty voxel ``(b, z, y, x)`` gets
``BEV[b, :, y // s, x // s] + HeightEmb(z)`` (:func:`pillar_lift`), the fusion blocks run on those
voxels, and voxels with the same ``(b, y, x)`` are summed back into a BEV map (:func:`voxels_to_bev`,
or :func:`voxels_to_bev_sparse` for a 2D sparse form).

Grids: voxel coords are ``(batch, z, y, x)`` on a grid with ``spatial_shape (D, H, W)``; a BEV map at
stride ``(sy, sx)`` of that grid has shape ``(B, C, ceil(H / sy), ceil(W / sx))`` and row/column
``(y // sy, x // sx)``.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import (
    INDEX_DTYPES,
    check_dtype,
    check_finite,
    check_floating,
    check_index_range,
    check_index_ranges,
    check_shape,
)
from mssf_blocks.checks.arguments import check_positive_int, check_triple
from mssf_blocks.checks.geometry import check_batch_column
from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.checks.arguments import check_stride2
from mssf_blocks.checks.tensors import check_coords

__all__ = [
    "pillar_lift",
    "voxels_to_bev",
    "voxels_to_bev_sparse",
    "voxelize_points",
    "bev_shape_for",
]



def bev_shape_for(grid_hw: Sequence[int], stride=1) -> Tuple[int, int]:
    """``(ceil(H / sy), ceil(W / sx))``: the BEV map shape at ``stride`` of a voxel grid ``(H, W)``."""
    sy, sx = check_stride2(stride)
    h, w = (int(v) for v in grid_hw)
    return (-(-h // sy), -(-w // sx))


def pillar_lift(
    bev: Tensor,
    coords: Tensor,
    height_embedding: Optional[Tensor] = None,
    stride=1,
) -> Tensor:
    """Lift BEV features into voxels: ``bev[b, :, y // sy, x // sx] + height_embedding[z]``.

    Args:
        bev: ``(B, C, H_b, W_b)`` floating BEV map (row = y, column = x).
        coords: ``(N, 4)`` integer ``(b, z, y, x)`` voxel indices; ``b < B``, ``y // sy < H_b``,
            ``x // sx < W_b`` and ``z < Z``.
        height_embedding: optional ``(Z, C)`` table, one vector per z index.
        stride: ``int`` or ``(sy, sx)``: the BEV map's stride relative to the voxel grid.

    Returns:
        ``(N, C)`` voxel features in the dtype of ``bev``. Differentiable in ``bev`` and
        ``height_embedding`` (the backward pass sums the gradients of voxels sharing a pillar).

    Example:
        >>> bev = torch.arange(4.0).reshape(1, 1, 2, 2)
        >>> coords = torch.tensor([[0, 1, 3, 2]], dtype=torch.int32)
        >>> pillar_lift(bev, coords, torch.tensor([[10.0], [20.0]]), stride=2)
        tensor([[23.]])
    """
    check_shape(bev, "bev", ("B", "C", "H_b", "W_b"))
    check_floating(bev, "bev")
    check_coords(coords)
    sy, sx = check_stride2(stride)
    b_, c, hb, wb = bev.shape
    if coords.device != bev.device:
        raise MSSFError(f"coords: expected device {bev.device} (of bev), got {coords.device}")
    c64 = coords.long()
    bi, zi = c64[:, 0], c64[:, 1]
    yi = torch.div(c64[:, 2], sy, rounding_mode="floor")
    xi = torch.div(c64[:, 3], sx, rounding_mode="floor")
    checks = [(bi, "coords[:, 0] (batch index)", b_, "bev.shape[0]"),
              (yi, f"coords[:, 2] // {sy} (BEV row)", hb, "bev.shape[2]"),
              (xi, f"coords[:, 3] // {sx} (BEV column)", wb, "bev.shape[3]")]
    if height_embedding is not None:
        check_shape(height_embedding, "height_embedding", (None, c))
        check_floating(height_embedding, "height_embedding")
        checks.append((zi, "coords[:, 1] (z index)", height_embedding.shape[0], "height_embedding.shape[0]"))
    check_index_ranges(checks)  # one host synchronisation for all (not two per check)
    # Only N x C values are read (no channels-last copy of the whole map); the backward sums the
    # gradients of voxels sharing a pillar. One image: index_select along the pixels of a free view of
    # it, (H_b * W_b, C) rows of channels-last memory or (C, H_b * W_b) planes otherwise (measured 30-55 %
    # less time than advanced indexing with (b, y, x) index tensors on the PointPillars maps of
    # benchmarks/detectors.py, one core; any other map keeps advanced indexing), and the embedding rows
    # with index_select too (5x faster than advanced indexing), the lifted rows added into them.
    out = None
    if b_ == 1:
        cells = yi * wb + xi
        try:
            if bev.stride(1) == 1 and c > 1:
                out = bev[0].permute(1, 2, 0).view(hb * wb, c).index_select(0, cells)
            else:
                out = bev[0].view(c, hb * wb).index_select(1, cells).t()  # (N, C) view of (C, N)
        except RuntimeError:  # (no such view of this map's strides)
            out = None
    if out is None:
        out = bev[bi, :, yi, xi]
    if height_embedding is None:
        return out.contiguous()
    return height_embedding.to(out.dtype).index_select(0, zi).add_(out)


def voxels_to_bev(
    features: Tensor,
    coords: Tensor,
    batch_size: int,
    bev_shape: Sequence[int],
    stride=1,
) -> Tensor:
    """Sum voxel features with the same ``(b, y // sy, x // sx)`` into a dense BEV map.

    Args:
        features: ``(N, C)`` floating voxel features.
        coords: ``(N, 4)`` integer ``(b, z, y, x)``; duplicate rows are summed like any others.
        batch_size: ``B``.
        bev_shape: ``(H_b, W_b)`` of the output (e.g. :func:`bev_shape_for` of the voxel grid).
        stride: ``int`` or ``(sy, sx)`` of the BEV map relative to the voxel grid.

    Returns:
        ``(B, C, H_b, W_b)``; cells without voxels are 0.
    """
    batch_size, hb, wb, idx = _bev_pillar_index(features, coords, batch_size, bev_shape, stride)
    b = coords[:, 0].long()
    out = features.new_zeros(batch_size, features.shape[1], hb, wb)
    return _add_into_pillars(out, b, idx - b * (hb * wb), features)


def _add_into_pillars(bev: Tensor, b: Tensor, cell: Tensor, features: Tensor, clear: bool = False) -> Tensor:
    """In place on ``bev (B, C, H_b, W_b)`` (NCHW or channels-last memory) and returned: ``features (N, C)``
    added, in row order, into the pillars ``(b, cell = y * W_b + x)``, whose values are zeroed first
    with ``clear``.

    Straight into a view of the map: no channels-first copy of a ``(B * H_b * W_b, C)`` table (an
    out-of-place index_put on the transposed view copied the map, and the reshape of its result copied
    it again: 22 -> 2 ms for 2,600 pillars of 64 channels on a 320 x 320 map, one core). One image:
    ``index_fill_`` / ``index_add_`` along the pixels of its ``(C, H_b * W_b)`` planes, 30-40 % less
    time than ``index_put_`` on the ``(B, H_b * W_b, C)`` view, which several images take (measured on
    the PointPillars maps of benchmarks/detectors.py, one core). Both sum in row order from the map's
    values: the same bits.
    """
    bsz, c, hb, wb = bev.shape
    flat = bev.view(bsz, c, hb * wb)  # (a view for NCHW and channels-last memory alike)
    if bsz == 1:
        if clear:
            flat[0].index_fill_(1, cell, 0.0)
        flat[0].index_add_(1, cell, features.t())
    else:
        rows = flat.transpose(1, 2)
        if clear:
            rows.index_put_((b, cell), rows.new_zeros(()))
        rows.index_put_((b, cell), features, accumulate=True)
    return bev


def _bev_pillar_index(features: Tensor, coords: Tensor, batch_size, bev_shape, stride) -> Tuple[int, int, int, Tensor]:
    """Validate the arguments of the voxels -> BEV functions; return ``(B, H_b, W_b, flat pillar index)``."""
    check_shape(features, "features", ("N", "C"))
    check_floating(features, "features")
    check_coords(coords, features.shape[0])
    batch_size = check_positive_int(batch_size, "batch_size")
    try:
        hb, wb = (int(v) for v in bev_shape)
    except (TypeError, ValueError):
        raise MSSFError(f"bev_shape: expected (H_b, W_b), got {bev_shape!r}") from None
    if hb <= 0 or wb <= 0:
        raise MSSFError(f"bev_shape: expected positive (H_b, W_b), got {bev_shape!r}")
    sy, sx = check_stride2(stride)
    return batch_size, hb, wb, _pillar_index(coords, batch_size, hb, wb, sy, sx)


def _pillar_index(coords: Tensor, batch_size: int, hb: int, wb: int, sy: int, sx: int) -> Tensor:
    c64 = coords.long()
    yi = torch.div(c64[:, 2], sy, rounding_mode="floor")
    xi = torch.div(c64[:, 3], sx, rounding_mode="floor")
    check_index_ranges([(c64[:, 0], "coords[:, 0] (batch index)", batch_size, "batch_size"),
                        (yi, f"coords[:, 2] // {sy} (BEV row)", hb, "bev_shape[0]"),
                        (xi, f"coords[:, 3] // {sx} (BEV column)", wb, "bev_shape[1]")])
    return (c64[:, 0] * hb + yi) * wb + xi


def voxels_to_bev_sparse(
    features: Tensor,
    coords: Tensor,
    batch_size: int,
    bev_shape: Sequence[int],
    stride=1,
) -> Tuple[Tensor, Tensor]:
    """Like :func:`voxels_to_bev` but only the occupied pillars: a 2D sparse BEV tensor.

    Returns:
        ``features (M, C)`` (sums per pillar) and ``coords (M, 3)`` int32 ``(b, y, x)`` at the BEV
        stride, one row per occupied pillar, sorted by ``(b, y, x)``.
    """
    batch_size, hb, wb, idx = _bev_pillar_index(features, coords, batch_size, bev_shape, stride)
    keys, inverse = torch.unique(idx, sorted=True, return_inverse=True)
    out = features.new_zeros(keys.numel(), features.shape[1]).index_add(0, inverse, features)
    b = torch.div(keys, hb * wb, rounding_mode="floor")
    rest = keys - b * hb * wb
    y = torch.div(rest, wb, rounding_mode="floor")
    x = rest - y * wb
    return out, torch.stack([b, y, x], dim=1).int()


def voxelize_points(
    points: Tensor,
    points_batch: Tensor,
    batch_size: int,
    voxel_size: Sequence[float],
    point_range_min: Sequence[float],
    point_range_max: Sequence[float],
    features: str = "mean",
) -> SparseVoxels:
    """Voxelise raw points into a :class:`SparseVoxels` with one row per non-empty voxel.

    Use the BEV grid's x/y cell size for ``voxel_size[:2]`` (the pillar size times the BEV stride, or
    the pillar size with ``PillarLift(stride=s)``) and any z resolution for ``voxel_size[2]``. The
    voxel index is ``floor((p - point_range_min) / voxel_size)`` - the same rule the centroid join in
    :func:`mssf_blocks.functional.geometry.voxel_centroids` uses, so every voxel holds its points.

    Points outside ``[point_range_min, point_range_max)`` are not in the grid and are left out (crop
    the range yourself first if that matters).

    Args:
        points: ``(P, F)`` floating points, ``F >= 3`` with ``x, y, z`` first.
        points_batch: ``(P,)`` integer sample of every point.
        batch_size: ``B``.
        voxel_size: ``(x, y, z)`` metres.
        point_range_min: ``(x, y, z)`` lower corner.
        point_range_max: ``(x, y, z)`` upper corner; ``(max - min) / voxel_size`` must be integers
            (within ``1e-6``), giving ``spatial_shape (D, H, W)``.
        features: ``"mean"`` - the mean of the ``F`` point columns of each voxel (``(N, F)``);
            ``"count"`` - the number of points (``(N, 1)``, dtype of ``points``).

    Returns:
        :class:`SparseVoxels` with unique int32 coords sorted by ``(b, z, y, x)``.
    """
    check_shape(points, "points", ("P", None))
    check_floating(points, "points")
    if points.shape[1] < 3:
        raise MSSFError(f"points: expected shape (P, >=3) with x, y, z first, got {tuple(points.shape)}")
    check_finite(points, "points")
    check_shape(points_batch, "points_batch", (points.shape[0],))
    check_dtype(points_batch, "points_batch", INDEX_DTYPES)
    batch_size = check_positive_int(batch_size, "batch_size")
    check_index_range(points_batch, "points_batch", batch_size, "batch_size")
    check_batch_column(points, points_batch)
    vs = check_triple(voxel_size, "voxel_size", float, positive=True)
    lo = check_triple(point_range_min, "point_range_min", float)
    hi = check_triple(point_range_max, "point_range_max", float)
    if features not in ("mean", "count"):
        raise MSSFError(f"features: expected 'mean' or 'count', got {features!r}")
    shape_xyz = []
    for axis, (a, b, v) in enumerate(zip(lo, hi, vs)):
        cells = (b - a) / v
        if not cells >= 1 or abs(cells - round(cells)) > 1e-6 * max(1.0, cells):
            raise MSSFError(
                f"point_range_max: expected (max - min) / voxel_size to be a positive integer on axis "
                f"{'xyz'[axis]}, got ({b} - {a}) / {v} = {cells}"
            )
        shape_xyz.append(int(round(cells)))
    w, h, d = shape_xyz
    dtype, device = points.dtype, points.device
    xyz = points[:, :3]
    base = torch.floor((xyz - torch.tensor(lo, dtype=dtype, device=device))
                       / torch.tensor(vs, dtype=dtype, device=device)).long()
    inside = (base >= 0).all(dim=1) & (xyz < torch.tensor(hi, dtype=dtype, device=device)).all(dim=1)
    inside &= (base < torch.tensor([w, h, d], device=device)).all(dim=1)
    base, pts, pb = base[inside], points[inside], points_batch[inside].long()
    keys = ((pb * d + base[:, 2]) * h + base[:, 1]) * w + base[:, 0]
    uniq, inverse = torch.unique(keys, sorted=True, return_inverse=True)
    m = uniq.numel()
    counts = torch.zeros(m, dtype=dtype, device=device).index_add_(0, inverse, torch.ones_like(keys, dtype=dtype))
    if features == "count":
        feats = counts[:, None]
    else:
        sums = torch.zeros(m, pts.shape[1], dtype=dtype, device=device).index_add_(0, inverse, pts)
        feats = sums / counts[:, None]
    x = uniq % w
    rest = torch.div(uniq, w, rounding_mode="floor")
    y = rest % h
    rest = torch.div(rest, h, rounding_mode="floor")
    z = rest % d
    b = torch.div(rest, d, rounding_mode="floor")
    coords = torch.stack([b, z, y, x], dim=1).int()
    return SparseVoxels(feats, coords, (d, h, w), batch_size, voxel_size=vs, point_range_min=lo)
