"""The levels of the CPU plans bagged in blocks of queries, and their sum over the levels.

The four bilinear corners of a block's points (:func:`_corner_cells`, :func:`_corner_weights`) are
made block by block. A raw-row level (plans ``"sample"`` / ``"direct"``) samples the ``D`` raw channels of every head's
corners and is projected per head afterwards; a projected level (plans ``"dense"`` / ``"project"``)
samples its head's ``d`` channels of a projected table. In forward both are bagged together in
blocks of queries (:func:`_sum_levels`), so that the ``(Q * M, D)`` raw samples never exist whole and
every block's corner arrays stay in cache.
"""

from __future__ import annotations

from typing import List, NamedTuple, Optional, Tuple

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from mssf_blocks import torch_versions
from mssf_blocks.functional.plan_costs import _RAW_CHUNK_BYTES
from mssf_blocks.functional.deform.touched.points import _LevelLoc

def _corner_cells(c00: Tensor, wp: int) -> Tensor:
    """``(Q, M, 4, P)`` cells of the four bilinear corners, offsets ``(0, 1, Wp, Wp + 1)`` from the
    top-left cells ``c00 (Q, M, P)`` (the order of :func:`_corner_weights`), in ``c00``'s dtype."""
    out = c00.new_empty(c00.shape[0], c00.shape[1], 4, c00.shape[2])
    out[:, :, 0] = c00
    for k, off in enumerate((1, wp, wp + 1), 1):
        torch.add(c00, off, out=out[:, :, k])
    return out


def _corner_weights(x: Tensor, y: Tensor, x0: Tensor, y0: Tensor, wo: Tensor) -> Tensor:
    """``(Q, M, 4, P)`` bilinear corner weights times the attention weights ``wo (Q, M, P)`` of the
    pixel coordinates ``x, y (Q, M, P)`` (floors ``x0, y0``), in the order of the cell offsets
    ``(0, 1, Wp, Wp + 1)``."""
    fx = x - x0  # carries d/dx; floor is piecewise constant
    fy = y - y0
    ay0, ay1 = (1.0 - fy) * wo, fy * wo
    ax0 = 1.0 - fx
    # Contiguous products: several times faster than one broadcasting product on the CPU. Without
    # autograd they are written straight into the output's slices (no four temporaries and no stack
    # copy: 1-2 % of the whole forward at 2,500 queries, benchmarks/msdff.py); out= takes no gradients.
    if torch.is_grad_enabled() and any(t.requires_grad for t in (fx, fy, wo)):
        return torch.stack((ay0 * ax0, ay0 * fx, ay1 * ax0, ay1 * fx), 2)
    out = fx.new_empty(fx.shape[0], fx.shape[1], 4, fx.shape[2])
    for k, (a, b) in enumerate(((ay0, ax0), (ay0, fx), (ay1, ax0), (ay1, fx))):
        torch.mul(a, b, out=out[:, :, k])
    return out


class _RawLevel(NamedTuple):
    """A raw-row level, ready to be bagged for any block of queries: ``lv`` its points, ``c00 (Q, M, P)``
    their top-left cells (:func:`_top_left_cells`) on the padded grid of width ``wp``, ``remap`` the
    flat cell -> table row map (``n_rows`` for a padding cell), ``table (rows, D)``; ``clamp``: the row
    out-of-map corners read with weight 0, or ``None`` when the table's last row is not finite
    (0 * NaN = NaN would reach voxels that do not read it, and their gradients): they are then left
    out of their bags (offsets; the compaction costs about a third of the bag's forward, hence only
    then). The corners' rows are looked up block by block (:func:`_bag_raw`): the same time as one
    lookup over all queries (measured in isolation, 0.47 ms a level at 2,500 queries), without a
    ``(Q, M, 4 * P)`` rows array of several MiB at 8,000 queries alive for the whole call."""

    lv: _LevelLoc
    c00: Tensor
    remap: Tensor
    wp: int
    table: Tensor
    n_rows: int
    clamp: Optional[int]


def _block_corners(level, start: int, stop: int) -> Tuple[Tensor, Tensor]:
    """``(n * M, 4 * P)`` table rows and bilinear x attention weights of the corners of the queries
    ``[start, stop)`` of a :class:`_RawLevel` or :class:`_ProjectedLevel` (the order of
    :func:`_corner_cells` / :func:`_corner_weights`); padding cells map to ``remap``'s padding row."""
    k = 4 * level.c00.shape[2]
    rows = level.remap.index_select(0, _corner_cells(level.c00[start:stop], level.wp).view(-1)).view(-1, k)
    return rows, _corner_weights(*(t[start:stop] for t in level.lv[:5])).view(-1, k)


def _bag_raw(raw: _RawLevel, start: int, stop: int):
    """``(n * M, D)`` raw samples (query-major) and ``(n, M, 1)`` in-map weight mass of the queries
    ``[start, stop)``."""
    m, k = raw.c00.shape[1], 4 * raw.c00.shape[2]
    rows, psw = _block_corners(raw, start, stop)
    # The in-map mask as 1.0 / 0.0 in the weights' type, written by the comparison itself: a bool mask
    # and a float-times-bool product each take a slow mixed-type loop (measured 2.5x slower for the two
    # at 512 queries); x * 1.0 and x * 0.0 are the same bits either way. (Fresh arrays: in place.)
    psw = psw.mul_(torch.ne(rows, raw.n_rows, out=torch.empty_like(psw)))
    if raw.clamp is not None:
        sampled = torch_versions.embedding_bag(rows.clamp_(max=raw.clamp), raw.table, per_sample_weights=psw, mode="sum")
    else:
        inside = rows != raw.n_rows  # (the compaction's index: rare, see _RawLevel)
        counts = inside.sum(1)
        offsets = torch.cumsum(counts, 0) - counts
        sampled = torch_versions.embedding_bag(rows[inside], raw.table, offsets=offsets, per_sample_weights=psw[inside],
                                  mode="sum")
    return sampled, psw.view(-1, m, k).sum(-1, keepdim=True)


class _ProjectedLevel(NamedTuple):
    """A projected level (plans ``"dense"`` / ``"project"``, forward only), ready to be bagged for any
    block of queries: ``lv`` its points, ``c00 (Q, M, P)`` their top-left cells with the head folded in
    (head ``h``'s cells offset by ``h`` times the padded grid's size), ``remap`` the flat (head, cell) ->
    row map of ``table ((rows + 1) * M, d)`` (row ``r * M + h``: head ``h``'s channels of projected row
    ``r``; padding cells read the last, zero row), ``wp`` the padded grid's width."""

    lv: _LevelLoc
    c00: Tensor
    remap: Tensor
    wp: int
    table: Tensor


def _bag_projected(lvl: _ProjectedLevel, start: int, stop: int) -> Tensor:
    """``(n, M, d)`` samples of the queries ``[start, stop)`` of a projected level."""
    rows, psw = _block_corners(lvl, start, stop)
    return torch_versions.embedding_bag(rows, lvl.table, per_sample_weights=psw, mode="sum").view(-1, lvl.c00.shape[1],
                                                                                     lvl.table.shape[1])


def _project_raw_block(raws: List[_RawLevel], start: int, stop: int, w_heads: Tensor,
                       b_heads: Optional[Tensor]) -> Tensor:
    """``(n, M, d)`` per-head projection (bias times mass included) of the raw samples of the queries
    ``[start, stop)`` summed over the levels ``raws``."""
    acc = mass = None
    for lvl in raws:
        part, part_mass = _bag_raw(lvl, start, stop)
        acc = part if acc is None else acc.add_(part)  # (in place: embedding_bag's backward keeps no output)
        mass = part_mass if mass is None else mass + part_mass
    m, dch = w_heads.shape[0], w_heads.shape[1]
    # head m of every query: a strided (n, D) batch of the query-major samples (BLAS reads it in place)
    out = torch.bmm(acc.view(-1, m, dch).transpose(0, 1), w_heads).transpose(0, 1)  # (n, M, d)
    return out if b_heads is None else torch.addcmul(out, mass, b_heads)  # (one pass for out + mass * b)


def _sum_levels(raws: List[_RawLevel], projected: List[_ProjectedLevel], w_all: Tensor, b_all: Optional[Tensor],
                m: int, needs_grad: bool, base: Optional[Tensor] = None) -> Tensor:
    """``(Q, M, d)`` sum over the levels: the ``projected`` levels' samples (forward only), the per-head
    projection of the raw samples of ``raws``, and ``base (Q, M, d)`` (levels sampled otherwise, if
    any; forward only: summed into in place), in the plans' (sorted) query order.

    Every level's corners are handled a block of queries at a time: the block's cells, rows and
    weights (``(block, M, 4 * P)`` each, a few hundred KiB) are reused from the heap block after
    block. Taken for all queries at once (as the projected levels were), they are several MiB each at
    8,000 queries, and under glibc's default allocator settings such temporaries come back as fresh
    pages on many calls (measured with the reference run between calls, 2,500 uniform queries of
    benchmarks/msdff.py: 4,300 page faults a call before, none after; 63.4 -> 61.6 ms).

    The bags are query-major (a query's heads one after another, the queries in image order): the
    rows that consecutive bags read then lie in one band of the image, which stays in cache, instead of
    every head sweeping the whole band again (measured 25-40 % faster bags on the 150-MiB P2 level at
    2,500-8,000 queries, one core). The queries are taken ``_RAW_CHUNK_BYTES`` of ``(block * M, D)``
    raw samples at a time: the whole ``(Q * M, D)`` block (65 MiB at 8,000 queries and 256 channels)
    would cost its size in memory and, above glibc's mmap threshold, its page faults on every call; a
    block of a few MiB is reused from the heap and stays in cache for the projection (measured 14-24 %
    faster forward at 8,000 voxels); the projected levels take the same blocks. With gradients every
    raw block is recomputed in backward (activation checkpointing): autograd then keeps the levels'
    corner rows instead of the raw samples and the corner weights of every block.
    """
    q = (raws or projected)[0].c00.shape[0]
    d, dch = w_all.shape[0] // m, w_all.shape[1]
    w_heads = w_all.view(m, d, dch).transpose(1, 2)
    b_heads = None if b_all is None else b_all.view(1, m, d)
    step = max(1, _RAW_CHUNK_BYTES // (m * dch * w_all.element_size()))
    if not needs_grad:  # each block summed straight into place (no concatenation, no separate sum)
        out = w_all.new_empty(q, m, d) if base is None else base
        for s in range(0, q, step):
            e = min(s + step, q)
            part = None
            for lvl in projected:  # (in level order, then the raw levels: the sums of the unblocked code)
                sampled = _bag_projected(lvl, s, e)
                part = sampled if part is None else part.add_(sampled)
            if raws:
                raw = _project_raw_block(raws, s, e, w_heads, b_heads)
                part = raw if part is None else part.add_(raw)
            if base is None:
                out[s:e] = part
            else:
                out[s:e].add_(part)
        return out
    if projected:
        raise RuntimeError("projected levels are sampled per block in forward only")  # (internal)
    outs = []
    for s in range(0, q, step):
        # (non-reentrant checkpointing recomputes from the same raws: no tensor needs passing)
        outs.append(checkpoint(_project_raw_block, raws, s, min(s + step, q), w_heads, b_heads,
                               use_reentrant=False, preserve_rng_state=False))
    out = outs[0] if len(outs) == 1 else torch.cat(outs, 0)
    out = out if base is None else base.add_(out)  # (no backward here needs the other levels' sum)
    return out
