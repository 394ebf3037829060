"""The order in which the CPU plans take the queries: by image, then along a Hilbert curve over the image.

Neighbouring queries then read neighbouring rows, still in cache, and a block of queries reads one
compact patch of the image (measurements: ``_SORT_CELL`` in ``functional/plan_costs.py``).
"""

from __future__ import annotations

import functools
import math
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.functional.plan_costs import _SORT_CELL

# The Hilbert curve is walked a few levels at a time: per level, the two bits of a cell (x, y) and
# the orientation of its sub-square (a swap of x and y, a complement of both: four states) give the
# level's digit of the curve index and the next state. _HILBERT_LEVELS levels at once are one lookup
# in a table of 4 * 4**levels entries (made once per device): 0.07 ms for 2,500 cells of 8 levels,
# against 0.5 ms for the level-by-level arithmetic (one core).
_HILBERT_LEVELS = 4


@functools.lru_cache(maxsize=None)
def _hilbert_table(levels: int, device: torch.device) -> Tuple[Tensor, Tensor]:
    """``(digits, states)``, each ``(4 * 4**levels,)`` int64, at ``(state * 2**levels + x) * 2**levels + y``
    for the ``levels`` bits ``x, y`` of a cell below a sub-square in ``state`` (bit 0: x and y swapped,
    bit 1: both complemented): the ``2 * levels`` bits of the curve index they add, and the state of
    the sub-square they lead to."""
    n = 1 << levels
    digits, states = [], []
    for state in range(4):
        for x in range(n):
            for y in range(n):
                st, digit = state, 0
                for b in range(levels - 1, -1, -1):
                    rx, ry = (x >> b) & 1, (y >> b) & 1
                    if st & 1:
                        rx, ry = ry, rx
                    if st & 2:
                        rx, ry = rx ^ 1, ry ^ 1
                    digit = 4 * digit + ((3 * rx) ^ ry)
                    if ry == 0:  # the sub-square is turned: swapped, and complemented when rx == 1
                        st ^= 1 | (rx << 1)
                digits.append(digit)
                states.append(st)
    return (torch.tensor(digits, dtype=torch.int64, device=device),
            torch.tensor(states, dtype=torch.int64, device=device))


def _hilbert_index(x: Tensor, y: Tensor, bits: int) -> Tensor:
    """Position of the integer cells ``x, y`` (int64, in ``[0, 2**bits)``) along the Hilbert curve that
    fills the ``2**bits``-sided square from ``(0, 0)`` to ``(2**bits - 1, 0)``: cells close on the
    curve are close in the plane (unlike a row-major or Z order, the curve never jumps)."""
    d = torch.zeros_like(x)
    state = torch.zeros_like(x)
    done = 0
    while done < bits:
        levels = (bits - done) % _HILBERT_LEVELS or _HILBERT_LEVELS  # (the top levels first)
        shift, mask = bits - done - levels, (1 << levels) - 1
        digits, states = _hilbert_table(levels, x.device)
        key = ((state << levels) | ((x >> shift) & mask)) << levels
        key |= (y >> shift) & mask
        d = (d << (2 * levels)) | digits.index_select(0, key)
        state = states.index_select(0, key)
        done += levels
    return d


def _sort_cells(locations: Tensor, sizes: Sequence[Tuple[int, int]], cell: float) -> Tuple[Tensor, Tensor, int]:
    """``(x, y, bits)``: the integer cells, in ``[0, 2**bits)``, of each query's first sampling location
    (near its reference point) on a grid of squares of about ``cell`` pixels of the finest of the
    levels of ``sizes`` ``(H_l, W_l)``, whose longer side spans the ``2**bits``-sided square."""
    h, w = max(sizes, key=lambda hw: hw[0] * hw[1])
    ref = locations[:, 0, 0, 0].detach().clamp(0.0, 1.0)
    longer = max(h, w, 1)
    bits = min(max(1, math.ceil(math.log2(max(longer / cell, 2.0)))), 15)
    scale = ((1 << bits) - 1) / longer  # (cells per pixel)
    return (ref[:, 0] * (w * scale)).round().long(), (ref[:, 1] * (h * scale)).round().long(), bits


def _spatial_order(image_index: Tensor, locations: Tensor, sizes: Sequence[Tuple[int, int]],
                   cell: float = _SORT_CELL) -> Tensor:
    """``(Q,)`` permutation of the queries by image, then along a Hilbert curve over the image
    (:func:`_hilbert_index`) of the cells (:func:`_sort_cells`) of their first sampling locations.

    The cells are squares of about ``cell`` pixels of the finest level: consecutive queries, and the
    queries of a block, then lie in one compact patch of the image, whose rows the bags read from cache
    (the order by bands of rows it replaced let a block span the image's width).
    """
    x, y, bits = _sort_cells(locations, sizes, cell)
    return torch.argsort(image_index * (1 << (2 * bits)) + _hilbert_index(x, y, bits))


def _inverse(order: Tensor, size: Optional[int] = None) -> Tensor:
    """The inverse of the permutation ``order``; with ``size`` (``order`` then takes ``len(order)`` of
    ``size`` items), the positions ``order`` leaves out map to ``len(order)``, one past its end."""
    n = order.numel()
    inverse = torch.empty_like(order) if size is None else torch.full((size,), n, dtype=order.dtype,
                                                                      device=order.device)
    inverse[order] = torch.arange(n, device=order.device)
    return inverse


def _query_order(image_index: Tensor, locations: Tensor, sizes: Sequence[Tuple[int, int]],
                 live: Optional[Tensor] = None) -> Tuple[Tensor, Tensor]:
    """``(order, restore)``: :func:`_spatial_order` and its inverse (which puts results back in the callers'
    order). With ``live`` (``(Q,)`` bool), ``order`` takes only the live queries, and ``restore`` sends
    every other query to row ``len(order)``, one past the results (for a zero row)."""
    order = _spatial_order(image_index, locations, sizes)
    if live is None:
        return order, _inverse(order)
    order = order[live[order]]
    return order, _inverse(order, live.numel())
