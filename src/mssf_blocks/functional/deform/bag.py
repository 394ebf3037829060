"""The embedding-bag path of ``ms_deform_sample`` (any ``Mv``, no projection): the four bilinear corners
of every point as rows of each level's ``(pixels, D)`` table, reduced by ``embedding_bag(mode="sum")``
weighted by ``bilinear weight * attention weight`` (never a gathered ``(corners, D)`` tensor); autograd
carries the per-corner weight gradient back to ``locations`` and ``weights``. Inputs unchecked (the
public functions check them)."""

from __future__ import annotations

import math
from typing import List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from mssf_blocks import torch_versions
from mssf_blocks.functional.deform.touched.order import _inverse
from mssf_blocks.functional.deform.touched.points import _pixel_coordinate, _rows
from mssf_blocks.functional.plan_costs import _STATIC_BAG_COST, _STATIC_BLOCK_BYTES

__all__ = ["STATIC_PLAN_QUERIES", "plan_queries", "sample", "sample_project_chunked", "sample_project_static",
           "static_blocks"]


def _index_dtype(values: Sequence[Tensor], mv: int) -> torch.dtype:
    # int32 rows halve the index memory and are read natively by embedding_bag.
    rows = max(v.shape[0] * mv * v.shape[-2] * v.shape[-1] for v in values)
    return torch.int32 if rows + 2 * max(v.shape[-1] for v in values) < 2**31 else torch.int64


def _level_corners(loc: Tensor, wts: Tensor, plane: Tensor, planes: int, h: int, w: int, idt: torch.dtype,
                   return_mass: bool) -> Tuple[Tensor, Tensor, Optional[Tensor]]:
    """One level's ``(A, B, 4, P)`` table rows and weights (``bilinear weight * attention weight``) of the four
    bilinear corners of the points ``loc (A, B, P, 2)`` with attention weights ``wts (A, B, P)`` (``A, B``:
    queries and heads in either order) on planes ``plane (A, B, 1)`` of a table of ``planes`` maps of
    ``h x w`` rows, and with ``return_mass`` the ``(A, B)`` in-map weight mass."""
    x = _pixel_coordinate(loc[..., 0], w)  # (A, B, P); the sizes are Python numbers: scalar operands
    y = _pixel_coordinate(loc[..., 1], h)
    x0 = x.detach().floor()
    y0 = y.detach().floor()
    fx = x - x0  # carries d/dx; floor is piecewise constant
    fy = y - y0
    # Per-axis corner weights, zero where the corner is outside the map (zero padding); the attention
    # weight is folded into the y factors so that each corner weight is one product.
    ax0 = (1.0 - fx) * ((x0 >= 0) & (x0 <= w - 1))
    ax1 = fx * ((x0 >= -1) & (x0 <= w - 2))
    ay0 = (1.0 - fy) * ((y0 >= 0) & (y0 <= h - 1)) * wts
    ay1 = fy * ((y0 >= -1) & (y0 <= h - 2)) * wts
    # Corner-major inside each bag, (A, B, 4, P): the order within a bag is free and this layout stacks in
    # blocks of P instead of interleaving single elements.
    psw = torch.stack((ay0 * ax0, ay0 * ax1, ay1 * ax0, ay1 * ax1), -2)
    mass = ((ay0 + ay1) * (ax0 + ax1)).sum(-1) if return_mass else None
    # Row of the top-left corner, (plane * h + y0) * w + x0, computed on points (4x fewer than corners)
    # after clamping x0, y0 to [-1, size] so that huge coordinates cannot overflow; the corners add
    # (0, 1, w, w + 1). A corner outside the map has weight 0 and any row inside the table will do, hence
    # the final clamp to the table.
    base = (plane * h + y0.clamp(-1.0, float(h)).to(idt)) * w + x0.clamp(-1.0, float(w)).to(idt)
    offsets = torch.tensor([0, 1, w, w + 1], dtype=idt, device=base.device).view(4, 1)
    rows = (base.unsqueeze(-2) + offsets).clamp_(0, planes * h * w - 1)
    return rows, psw, mass


def sample(
    values: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor, return_mass: bool,
    query_major: bool = False,
) -> Union[Tensor, Tuple[Tensor, Tensor]]:
    q, m, _, p, _ = locations.shape
    mv, d = values[0].shape[1:3]
    dev = locations.device
    # Level by level, head-major bags, (M, Q, P) points: the embedding-bag output comes out as (M, Q, D),
    # the layout a per-head projection (bmm) wants. With query_major, (Q, M, P) instead: the bags of a
    # query's heads are neighbours, and read rows near the same reference point while they are in cache
    # (the static path: 0.88-0.94 of the time, benchmarks/static_path.py's MSDFF cases); the output is then
    # (Q, M, D) memory.
    order = (2, 0, 1) if query_major else (2, 1, 0)
    locs = locations.permute(*order, 3, 4)  # (L, M, Q, P, 2) or (L, Q, M, P, 2)
    wts = weights.permute(*order, 3)
    idt = _index_dtype(values, mv)
    heads = torch.arange(m, device=dev, dtype=idt) if mv > 1 else torch.zeros(m, dtype=idt, device=dev)
    if query_major:
        plane = (image_index.to(idt)[:, None] * mv + heads[None, :]).unsqueeze(-1)  # (Q, M, 1)
    else:
        plane = (image_index.to(idt)[None, :] * mv + heads[:, None]).unsqueeze(-1)  # (M, Q, 1)
    out = mass = None
    for lvl, val in enumerate(values):
        rows, psw, part_mass = _level_corners(locs[lvl], wts[lvl], plane, val.shape[0] * mv, val.shape[-2],
                                              val.shape[-1], idt, return_mass)
        mass = part_mass if mass is None else mass + part_mass
        # (I, Mv, D, H, W) -> (I * Mv * H * W, D): a free view for channels-last features; otherwise one
        # layout copy of this level (embedding_bag reads a strided table several times slower than a copy)
        table = _row_major(val).permute(0, 1, 3, 4, 2).reshape(-1, d)
        # (rows follow the locations' memory order: a copy where that is not the bags' order)
        part = torch_versions.embedding_bag(rows.reshape(m * q, p * 4), table,
                                            per_sample_weights=psw.reshape(m * q, p * 4), mode="sum")  # (M * Q, D)
        if out is None:
            out = part
        else:
            out += part  # in place: embedding_bag's backward does not need its output
    if return_mass:
        mass = mass if query_major else mass.t()  # (Q, M)
    out = out.view(q, m, d) if query_major else out.view(m, q, d).transpose(0, 1)  # (Q, M, D)
    return (out, mass) if return_mass else out


def _sample_project_level(
    locations: Tensor,
    weights: Tensor,
    image_index: Tensor,
    proj_weight: Tensor,
    proj_bias: Optional[Tensor],
    value: Tensor,
) -> Tensor:
    """One level of :func:`ms_deform_sample_project` for ``locations (Q, M, 1, P, 2)``."""
    sampled, mass = sample([value], image_index, locations, weights, True)
    # sampled is a (Q, M, D) view of head-major (M, Q, D) memory: the per-head bmm reads it in place.
    out = torch.bmm(sampled.transpose(0, 1), proj_weight.transpose(1, 2)).transpose(0, 1)  # (Q, M, d)
    if proj_bias is not None:
        out = out + mass[..., None] * proj_bias
    return out


# The static path plans its levels for this many queries when the count is symbolic (torch.export with a
# dynamic voxel count): a radar frame has 10^3-10^4 voxels; the plan changes the cost, never the result.
STATIC_PLAN_QUERIES = 2500


def plan_queries(q) -> int:
    """The query count a static plan is made for: ``q``, or ``STATIC_PLAN_QUERIES`` where ``q`` is symbolic."""
    return q if isinstance(q, int) else STATIC_PLAN_QUERIES


def _row_major(level: Tensor) -> Tensor:
    """``level (I, Mv, D, H, W)`` over ``(I, Mv, H, W, D)`` memory, the row table :func:`sample` reads in place:
    ``level`` itself when it is in that memory (channels-last features), else one layout copy (the static
    path makes it once, before its blocks of queries, so that :func:`sample` finds it in place)."""
    rows = level.permute(0, 1, 3, 4, 2)
    return level if rows.is_contiguous() else rows.contiguous().permute(0, 1, 4, 2, 3)


def _levels(t: Tensor, chosen: List[int]) -> Tensor:
    """The levels ``chosen`` (ascending) of ``t (Q, M, L, ...)``: a view where they are consecutive."""
    if chosen == list(range(chosen[0], chosen[0] + len(chosen))):
        return t.narrow(2, chosen[0], len(chosen))
    return t.index_select(2, torch.tensor(chosen, device=t.device))


def static_blocks(q: int, m: int, c: int, itemsize: int) -> int:
    """How many blocks of queries the static path bags ``q`` queries in: ``plan_costs._STATIC_BLOCK_BYTES`` of
    ``(queries * m, c)`` raw samples each."""
    return max(1, math.ceil(q * m * c * itemsize / _STATIC_BLOCK_BYTES))


def _dense_pays(level: Tensor, q: int, m: int, p: int, d: int) -> bool:
    """Whether projecting every pixel of ``level (I, 1, C, H, W)`` and bagging ``d`` channels per head costs
    less than bagging the ``C`` raw channels of every corner (in GEMM multiply-adds, ``plan_costs``)."""
    c = level.shape[2]
    pixels = level.shape[0] * level.shape[-2] * level.shape[-1]
    corners = plan_queries(q) * m * p * 4
    return pixels * c * m * d + corners * d * _STATIC_BAG_COST < corners * c * _STATIC_BAG_COST


def _project_level(level: Tensor, proj_weight: Tensor, proj_bias: Tensor) -> Tensor:
    """``level (I, 1, C, H, W)`` projected per head: an ``(I, M, d, H, W)`` view of ``(I, M, H, W, d)`` memory,
    the row table embedding_bag reads in place."""
    m, d, c = proj_weight.shape
    i, _, _, h, w = level.shape
    out = F.linear(level[:, 0].permute(0, 2, 3, 1), proj_weight.reshape(m * d, c), proj_bias.reshape(m * d))
    return out.view(i, h, w, m, d).permute(0, 3, 1, 2, 4).contiguous().permute(0, 1, 4, 2, 3)


def _row_order(image_index: Tensor, locations: Tensor, sizes: Sequence[Tuple[int, int]]) -> Tensor:
    """``(Q,)`` permutation of the queries by image, then by bands of 8 pixel rows of the finest level, then
    along ``u`` (of their first sampling location): neighbouring queries read neighbouring rows. (The
    touched plans' Hilbert order, ``touched/order.py``, reads a cached table, which ``torch.jit.trace``
    records as a different constant on every call.)"""
    h, w = max(sizes, key=lambda hw: hw[0] * hw[1])
    ref = locations[:, 0, 0, 0].detach().clamp(0.0, 1.0)
    band = (ref[:, 1] * (h / 8.0)).floor()
    return torch.argsort((image_index.to(ref.dtype) * (h / 8.0 + 1.0) + band) * 2.0 + ref[:, 0])


def sample_project_static(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                          proj_weight: Tensor, proj_bias: Tensor) -> Tensor:
    """``(Q, M, d)``: the op's formula with static shapes and a cost in the queries, not the pixels.

    The static-shape path's MSDFF sampling (graph capture, ``static_path()``): fixed-size embedding bags
    (one per (head, query) and level, weights ``bilinear * attention``: no ``nonzero``, no data-dependent
    size, a query's image a row offset) over, per level, the cheaper of two exact tables (the touched
    plans' cost model, ``plan_costs``; planned for ``STATIC_PLAN_QUERIES`` queries when their count is
    symbolic):

    * the raw ``C``-channel rows of the level ``(I, 1, C, H_l, W_l)`` (a free view of channels-last
      memory, one layout copy otherwise), then head ``m``'s rows of the value projection
      ``proj_weight (M, d, C)`` plus ``proj_bias (M, d)`` times the in-image bilinear weight mass.
      Exact: sampling is linear, ``sum_k w_k (W x_k + b) = W (sum_k w_k x_k) + b sum_k w_k`` with the
      sums over the corners inside the map (zero padding: in the project-first formulation a corner
      outside reads a zero *projected* pixel, bias included). Cost ``O(Q * M * P * 4 * C)``;
    * every pixel projected (``O(H_l * W_l * C * M * d)``, a small level), ``d`` channels per head bagged.

    The queries are taken in image order (:func:`_row_order`): neighbouring bags read neighbouring rows;
    each bag's sum is the same in any order. They are bagged in :func:`static_blocks` blocks of one size
    (``plan_costs._STATIC_BLOCK_BYTES`` of raw samples; planned like the levels), a fixed count of views,
    so that the voxel count stays one dynamic axis under ``torch.export``.
    """
    q, m, _, p, _ = locations.shape
    d, c = proj_weight.shape[1], levels[0].shape[2]
    sizes = [tuple(lvl.shape[-2:]) for lvl in levels]
    order = _row_order(image_index, locations, sizes)
    k = static_blocks(plan_queries(q), m, c, locations.element_size())
    # k blocks of s queries in row order: the block's raw samples and corner arrays stay in cache, and its
    # temporaries (a few MiB) are reused from the heap, where one block of every query (65 MiB of samples
    # at 8,000 voxels) comes back as fresh pages on each call. k * s >= q rows are gathered (the last query
    # repeated, its copies dropped at the end), so that every block is a view of one size s >= 2; with a
    # symbolic q, s is one floor division (s = q // k + 2 would make torch.export guard on
    # (2 * s) % s == 0, which it cannot prove for such a sum, when a (s * M) dim is split into (s, M)).
    s = (q + 2 * k - 1) // k if k > 1 else q
    take = order if k == 1 else order.index_select(0, torch.arange(k * s, device=order.device).clamp(max=q - 1))
    image_index, locations, weights = (_rows(t, take) for t in (image_index, locations, weights))
    dense = [_dense_pays(lvl, q, m, p, d) for lvl in levels]
    raw = [i for i, dn in enumerate(dense) if not dn]
    projected = [i for i, dn in enumerate(dense) if dn]

    def in_blocks(chosen: List[int]) -> Tuple[Tensor, Tensor]:
        loc, wt = _levels(locations, chosen), _levels(weights, chosen)
        return loc.view(k, s, *loc.shape[1:]), wt.view(k, s, *wt.shape[1:])

    # (the tables are made once, before the blocks: an NCHW level's row-table copy, a projected level)
    raw_tables = [_row_major(levels[i]) for i in raw]
    projected_tables = [_project_level(levels[i], proj_weight, proj_bias) for i in projected]
    raw_loc, raw_wt = in_blocks(raw) if raw else (None, None)
    projected_loc, projected_wt = in_blocks(projected) if projected else (None, None)
    image_index = image_index.view(k, s)
    blocks = []
    for b in range(k):
        out = None
        if raw:
            sampled, mass = sample(raw_tables, image_index[b], raw_loc[b], raw_wt[b], True, query_major=True)
            out = torch.bmm(sampled.transpose(0, 1), proj_weight.transpose(1, 2)).transpose(0, 1)  # (s, M, d)
            out = out + mass[..., None] * proj_bias
        if projected:
            part = sample(projected_tables, image_index[b], projected_loc[b], projected_wt[b], False, query_major=True)
            out = part if out is None else out + part
        blocks.append(out)
    out = blocks[0] if k == 1 else torch.cat(blocks)
    return out.index_select(0, _inverse(order))


def sample_project_chunked(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                           proj_weight: Tensor, proj_bias: Optional[Tensor], chunk_size: Optional[int]) -> Tensor:
    """``ms_deform_sample_project``'s ``"chunked"`` method: this path per (chunk of queries, level), then
    the per-head projection; with gradients each block is recomputed in backward (checkpointing)."""
    q = locations.shape[0]
    step = q if chunk_size is None else chunk_size
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in [locations, weights, proj_weight, proj_bias, *levels]
    )
    # One (chunk, level) block at a time: only its corners and one (M, chunk, D) sampled block are
    # alive; with gradients, each block is recomputed in backward instead of stored.
    parts = []
    for start in range(0, max(q, 1), max(step, 1)):
        sl = slice(start, start + step)
        acc = None
        for lvl, val in enumerate(levels):
            args = (locations[sl, :, lvl : lvl + 1], weights[sl, :, lvl : lvl + 1], image_index[sl],
                    proj_weight, proj_bias, val)
            if needs_grad and chunk_size is not None:
                part = checkpoint(_sample_project_level, *args, use_reentrant=False)
            else:
                part = _sample_project_level(*args)
            acc = part if acc is None else acc + part
        parts.append(acc)
    return parts[0] if len(parts) == 1 else torch.cat(parts, 0)
