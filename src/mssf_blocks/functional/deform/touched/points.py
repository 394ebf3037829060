"""The sampling points of the CPU plans: every level's points in one contiguous ``(Q, L, 2, M, P)``
block of pixel coordinates (:func:`_sorted_points`), one level's :class:`_LevelLoc` (:func:`_level`).
Query-major: a query's heads are adjacent.
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Sequence, Tuple

import torch
from torch import Tensor

def _pixel_coordinate(loc: Tensor, size: Tensor, inplace: bool = False) -> Tensor:
    """Pixel coordinates of normalised locations on a level of ``size`` pixels (broadcast), in place on
    ``loc`` with ``inplace`` (a private copy; no new tensor per step)."""
    # Bit for bit the float operations of grid_sample (grid = 2*loc - 1, then ((grid + 1) * size - 1) / 2
    # with align_corners=False), so that floor() -- and hence the one-sided gradient at integer pixel
    # coordinates -- agrees with the reference path. The factors 2 and 1/2 are dropped: scaling by a
    # power of two is exact and commutes with rounding (no overflow or subnormal results at finite
    # locations and sizes >= 1), so fl(fl(2l - 1) + 1) = 2 fl(fl(l - 1/2) + 1/2) and
    # fl(fl(2b * s) - 1) / 2 = fl(fl(b * s) - 1/2): four passes instead of six (checked equal on every
    # pixel boundary +- 4 ulp and 10^8 random locations, float32 and float64).
    shifted = loc.sub_(0.5) if inplace else loc - 0.5
    return shifted.add_(0.5).mul_(size).sub_(0.5)


def _rows(t: Tensor, index: Tensor) -> Tensor:
    """``t.index_select(0, index)``, gathered in ``t``'s memory order: the other dimensions are permuted by
    decreasing stride for the gather and back after it (a view). On the CPU, ``index_select`` of a
    permuted view, such as MSDFF's ``(Q, M, L, P, 2)`` locations over ``(Q, L, 2, M, P)`` memory, walks
    its strides element by element: 6.4 ms against 0.09 ms for its rows as whole runs, and 9.3 against
    1.1 ms with the backward (3,065 of 4,100 queries, one core). Equal values and gradients."""
    perm = [0, *sorted(range(1, t.dim()), key=lambda i: -t.stride(i))]  # (stable: equal strides keep their order)
    if perm == list(range(t.dim())):
        return t.index_select(0, index)
    back = [perm.index(i) for i in range(t.dim())]
    return t.permute(perm).index_select(0, index).permute(back)


def _wide(t: Tensor) -> Tensor:
    """``t`` with the bytes of its last dimension viewed as the widest elements (16, 8 or 4 bytes) that
    divide them, or ``t`` itself when none does, its memory does not allow the view, or autograd
    records it (a dtype view is not differentiable).

    For copies only (gathers, permutes): the bits are moved, never computed on. A copy whose innermost
    run is short (e.g. the ``P = 4`` points of a head) pays PyTorch's loop overhead per run and per
    element; as one 16-byte element per run it is a plain strided copy (measured 2.5x faster for the
    ``(Q, M, L, P) -> (Q, L, M, P)`` weights at 8,000 queries, one core).
    """
    if t.dim() == 0 or (t.requires_grad and torch.is_grad_enabled()):
        return t
    size = t.shape[-1] * t.element_size()
    for dtype in (torch.complex128, torch.int64, torch.int32):
        if dtype.itemsize > t.element_size() and size % dtype.itemsize == 0:
            try:
                return t.view(dtype)
            except RuntimeError:  # (strides or storage offset not a multiple of the wider element)
                continue
    return t


class _LevelLoc(NamedTuple):
    """One level's sampling points in the layout of the ``"touched"`` plans: ``x, y (Q, M, P)`` pixel
    coordinates (differentiable; each query's ``M * P`` values contiguous), ``x0, y0`` their floors
    (detached), ``wo (Q, M, P)`` attention weights; ``loc (Q, M, P, 2)`` / ``wt (Q, M, P)``: the same
    points in the callers' layout, for the plans that sample with ``F.grid_sample`` (``None`` when none
    will)."""

    x: Tensor
    y: Tensor
    x0: Tensor
    y0: Tensor
    wo: Tensor
    loc: Optional[Tensor] = None
    wt: Optional[Tensor] = None


def _sorted_points(locations: Tensor, weights: Tensor, sizes: Sequence[Tuple[int, int]],
                   order: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """Every level's points of ``locations (Q, M, L, P, 2)``, ``weights (Q, M, L, P)`` (queries taken in
    ``order``, if given) on levels of ``sizes`` ``(H_l, W_l)``: ``(Q, L, 2, M, P)`` pixel coordinates
    (:func:`_pixel_coordinate`, in place on the copy) and ``(Q, L, M, P)`` weights, both
    contiguous; :func:`_level` takes one level's :class:`_LevelLoc` out of them.

    Per level and axis, the points of all heads of a query are then one contiguous run: the twenty or so
    elementwise operations a level does before its first row is read each ran 3-4x slower on strided
    views of the callers' layout (measured on one core at 8,000 queries). Locations that already are a
    view of ``(Q, L, 2, M, P)`` memory (what :meth:`MSDFF.sampling_locations_and_weights
    <mssf_blocks.MSDFF.sampling_locations_and_weights>` returns) are taken by whole rows; others are
    gathered by rows, then transposed in one copy (2x faster than a strided gather per level).
    """
    lp = locations.permute(0, 2, 4, 1, 3)  # (a private copy: the pixel coordinates are made in place on it)
    lp = lp.clone(memory_format=torch.contiguous_format) if order is None else _rows(lp, order).contiguous()
    wts = weights if order is None else _rows(weights, order)
    wide = _wide(wts)  # (a head's P weights as one element, when autograd does not record them)
    moved = wide.permute(0, 2, 1, 3).contiguous()
    wts = moved if wide is wts else moved.view(wts.dtype)  # (a dtype view, even to the same type, drops autograd)
    size = torch.tensor([[float(w), float(h)] for h, w in sizes], dtype=lp.dtype,
                        device=lp.device).view(1, len(sizes), 2, 1, 1)
    return _pixel_coordinate(lp, size, inplace=True), wts


def _live_queries(locations: Tensor, sizes: Sequence[Tuple[int, int]]) -> Tensor:
    """``(Q,)`` bool: the queries of ``locations (Q, M, L, P, 2)`` that may read a pixel.

    A point reads nothing when, on its level, its pixel coordinate ``x = u * W - 0.5`` is below ``-1``
    or at least ``W`` (both of its columns outside the map), or the same holds for ``y``: its bilinear
    value is then zero, and so are its gradients (zero padding: they stay zero in a neighbourhood). A
    query all of whose points read nothing has a zero output and zero gradients w.r.t. every input, so
    the plans may leave it out. The test here keeps a half-pixel margin on each side (``u`` in
    ``[-1 / W, 1 + 1 / W]``, far beyond float rounding), and keeps NaN: only queries that certainly
    read nothing are dropped, e.g. MSDFF's invalid (voxel, camera) pairs, which the static layout
    places at ``uv = -1``.
    """
    lp = locations.detach().permute(0, 2, 4, 1, 3)  # (Q, L, 2, M, P): contiguous for MSDFF's locations
    half = torch.tensor([[0.5 + 1.0 / w, 0.5 + 1.0 / h] for h, w in sizes], dtype=lp.dtype, device=lp.device)
    # |u - 1/2| > 1/2 + 1/W, as 0 / 1 in the floating type (NaN: 0): 10x faster than boolean operations
    outside = (lp - 0.5).abs_().gt_(half.view(1, len(sizes), 2, 1, 1))
    either = outside[:, :, 0].add(outside[:, :, 1])  # (Q, L, M, P): 0 where the point may read
    return either.reshape(either.shape[0], -1).amin(dim=1) == 0


def _level(xy: Tensor, wts: Tensor) -> _LevelLoc:
    """One level of :func:`_sorted_points`' output, ``xy (Q, 2, M, P)`` and ``wts (Q, M, P)``, as a
    :class:`_LevelLoc` (``loc``/``wt`` left ``None``)."""
    x, y = xy.unbind(1)
    return _LevelLoc(x, y, x.detach().floor(), y.detach().floor(), wts)


def _level_points(locations: Tensor, weights: Tensor, sizes: Sequence[Tuple[int, int]],
                  order: Optional[Tensor] = None) -> List[_LevelLoc]:
    """Every level's :class:`_LevelLoc` (:func:`_sorted_points`, then :func:`_level` per level).

    The levels and axes are taken with ``unbind``, not one index per level and axis: with gradients,
    each index's backward writes its part into a zero tensor of the whole ``(Q, L, 2, M, P)`` block and
    the parts are summed, where an ``unbind``'s backward stacks them once (4 levels, 3,065 queries, one
    core: 4.2 -> 1.6 ms; the same gradient)."""
    xy, wts = _sorted_points(locations, weights, sizes, order)
    return [_level(lvl_xy, lvl_wts) for lvl_xy, lvl_wts in zip(xy.unbind(1), wts.unbind(1))]
