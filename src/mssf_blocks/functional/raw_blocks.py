"""Bilinear corners of the ``"touched"`` plans, and the raw-row plans' blocks of queries.

A raw-row level (plans ``"sample"`` / ``"direct"`` of :mod:`~mssf_blocks.functional.touched`) samples
the ``D`` raw channels of every head's corners and is projected per head afterwards; the levels are
bagged together in blocks of queries (:func:`_project_raw_levels`), so that the ``(M * Q, D)`` raw
samples never exist whole.
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .plan_costs import _RAW_CHUNK_BYTES


def _pixel_coordinate(loc: Tensor, size: Tensor) -> Tensor:
    # The exact float operations of grid_sample (grid = 2*loc - 1, unnormalise with
    # align_corners=False) so that floor() -- and hence the one-sided gradient at integer pixel
    # coordinates -- agrees bit for bit with the reference path.
    return ((2.0 * loc - 1.0 + 1.0) * size - 1.0) * 0.5  # (* 0.5 is / 2 exactly, and faster)


def _corner_weights(lo: Tensor, wo: Tensor, h: int, w: int, x: Optional[Tensor] = None,
                    y: Optional[Tensor] = None) -> Tensor:
    """``(M, Q, 4, P)`` bilinear corner weights times the attention weights ``wo (M, Q, P)`` of the
    normalised locations ``lo (M, Q, P, 2)`` on an ``h x w`` level, in the order of the cell offsets
    ``(0, 1, Wp, Wp + 1)`` (``x, y``: their pixel coordinates, if already computed)."""
    x = _pixel_coordinate(lo[..., 0], w) if x is None else x
    y = _pixel_coordinate(lo[..., 1], h) if y is None else y
    fx = x - x.detach().floor()  # carries d/dx; floor is piecewise constant
    fy = y - y.detach().floor()
    ay0, ay1 = (1.0 - fy) * wo, fy * wo
    ax0, ax1 = 1.0 - fx, fx
    # Stacks of contiguous products: several times faster than one broadcasting product on the CPU.
    return torch.stack((ay0 * ax0, ay0 * ax1, ay1 * ax0, ay1 * ax1), 2)


class _RawLevel(NamedTuple):
    """A raw-row level, ready to be bagged for any block of queries: ``lo (M, Q, P, 2)`` locations,
    ``wo (M, Q, P)`` attention weights, ``rows (M, Q, 4 * P)`` table rows of the corners (``n_rows``
    for a corner outside the map), ``table (rows, D)``; ``clamp``: the row out-of-map corners read
    with weight 0, or ``None`` when the table's last row is not finite (0 * NaN = NaN would reach
    voxels that do not read it, and their gradients): they are then left out of their bags
    (offsets; the compaction costs about a third of the bag's forward, hence only then)."""

    lo: Tensor
    wo: Tensor
    rows: Tensor
    table: Tensor
    h: int
    w: int
    n_rows: int
    clamp: Optional[int]


def _bag_raw(raw: _RawLevel, start: int, stop: int):
    """``(M * n, D)`` raw samples and ``(M, n, 1)`` in-map weight mass of the queries ``[start, stop)``."""
    m, _, k = raw.rows.shape
    psw = _corner_weights(raw.lo[:, start:stop], raw.wo[:, start:stop], raw.h, raw.w).view(-1, k)
    rows = raw.rows[:, start:stop].reshape(-1, k)
    inside = rows != raw.n_rows
    psw = psw * inside
    if raw.clamp is not None:
        sampled = F.embedding_bag(rows.clamp(max=raw.clamp), raw.table, per_sample_weights=psw, mode="sum")
    else:
        counts = inside.sum(1)
        offsets = torch.cumsum(counts, 0) - counts
        sampled = F.embedding_bag(rows[inside], raw.table, offsets=offsets, per_sample_weights=psw[inside],
                                  mode="sum")
    return sampled, psw.view(m, -1, k).sum(-1, keepdim=True)


def _project_raw_block(raws: List[_RawLevel], start: int, stop: int, w_heads: Tensor,
                       b_heads: Optional[Tensor]) -> Tensor:
    """``(M, n, d)`` per-head projection (bias times mass included) of the raw samples of the queries
    ``[start, stop)`` summed over the levels ``raws``."""
    acc = mass = None
    for lvl in raws:
        part, part_mass = _bag_raw(lvl, start, stop)
        acc = part if acc is None else acc.add_(part)  # (in place: embedding_bag's backward keeps no output)
        mass = part_mass if mass is None else mass + part_mass
    m, dch = w_heads.shape[0], w_heads.shape[1]
    out = torch.bmm(acc.view(m, -1, dch), w_heads)
    return out if b_heads is None else out + mass * b_heads


def _project_raw_levels(raws: List[_RawLevel], w_all: Tensor, b_all: Optional[Tensor], m: int,
                        needs_grad: bool) -> Tensor:
    """``(M, Q, d)`` per-head projection of the raw samples of ``raws`` summed over the levels.

    The queries are taken ``_RAW_CHUNK_BYTES`` of ``(M * block, D)`` samples at a time: the whole
    ``(M * Q, D)`` block (65 MiB at 8,000 queries and 256 channels) would cost its size in memory and,
    above glibc's mmap threshold, its page faults on every call; a block of a few MiB is reused from
    the heap and stays in cache for the projection (measured 14-24 % faster forward at 8,000 voxels).
    With gradients every block is recomputed in backward (activation checkpointing): autograd then
    keeps the levels' corner rows instead of the raw samples and the corner weights of every block.
    """
    q = raws[0].rows.shape[1]
    dch = raws[0].table.shape[1]
    d = w_all.shape[0] // m
    w_heads = w_all.view(m, d, dch).transpose(1, 2)
    b_heads = None if b_all is None else b_all.view(m, 1, d)
    step = max(1, _RAW_CHUNK_BYTES // (m * dch * raws[0].table.element_size()))
    outs = []
    for s in range(0, q, step):
        args = (raws, s, min(s + step, q), w_heads, b_heads)
        if needs_grad:  # (non-reentrant checkpointing recomputes from the same raws: no tensor needs passing)
            outs.append(checkpoint(_project_raw_block, *args, use_reentrant=False, preserve_rng_state=False))
        else:
            outs.append(_project_raw_block(*args))
    return outs[0] if len(outs) == 1 else torch.cat(outs, 1)
