"""One level of the CPU plans: the cheapest exact plan by the cost model, and its table.

Per level, the pixels that some in-map bilinear corner reads are marked (``U`` of them) and the
cheapest exact plan is run: project every pixel (``"dense"``), project only the touched pixels
(``"project"``), or sample the touched pixels' raw channels from a gathered table (``"sample"``) or in
place for channels-last levels (``"direct"``) and project per head. The level's raw rows (its
``(pixels, D)`` row table, the touched rows gathered and projected in pieces) are read here too. The
cost constants live in ``functional/plan_costs.py``. The points' top-left corners are located on the
level padded by 2 pixels (:func:`_top_left_cells`) and the pixels they read marked (:func:`_read_pixels`).
"""

from __future__ import annotations

from typing import Iterator, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.plan_costs import (
    _BAG_BACKWARD,
    _BAG_COST,
    _COPY_COST,
    _DIRECT_BAG_COST,
    _FILL_COST,
    _GATHER_COST,
    _GRID_SAMPLE_COST,
    _PROJECT_CHUNK,
)
from mssf_blocks.functional.deform.touched.blocks import _bag_projected, _bag_raw, _ProjectedLevel, _RawLevel
from mssf_blocks.functional.deform.touched.points import _LevelLoc

def _top_left_cells(lv: _LevelLoc, image_index: Tensor, num_images: int, h: int, w: int) -> Tensor:
    """``(Q, M, P)`` int64 cell of every point's top-left bilinear corner on its image's ``h x w`` level
    padded by 2 pixels on every side, the corner clamped to ``[-2, W]`` x ``[-2, H]`` (which keeps every
    in-map decision: ``x0 = -2`` and ``x0 = W`` have both corners outside) so that all four corners
    ``(0, 1, Wp, Wp + 1)`` away have a cell. Computed in the floating type while every cell id is an
    exact integer there (three operations instead of seven in int64)."""
    hp, wp = h + 4, w + 4
    xc = lv.x0.clamp(-2.0, float(w))
    yc = lv.y0.clamp(-2.0, float(h))
    exact = 2**53 if xc.dtype == torch.float64 else 2**24  # (float32 or float64: the sampling dtypes)
    if num_images * hp * wp < exact:
        base = ((image_index * hp + 2) * wp + 2).to(xc.dtype).view(-1, 1, 1)
        return (yc * wp).add_(xc).add_(base).long()
    return (image_index.view(-1, 1, 1) * hp + yc.long() + 2) * wp + xc.long() + 2


def _read_pixels(c00: Tensor, num_images: int, h: int, w: int) -> Tensor:
    """``(I, H, W)`` bool: the in-map pixels that some bilinear corner of the points with top-left cells
    ``c00`` (:func:`_top_left_cells`) reads. The top-left cells are marked in the padded grid (one write
    per point, not per corner) and a pixel is read iff its cell or the one left, above or above-left of
    it is marked."""
    hp, wp = h + 4, w + 4
    mark = torch.zeros(num_images * hp * wp, dtype=torch.bool, device=c00.device)
    try:
        mark.index_fill_(0, c00.reshape(-1), 1)  # (not True: a bool scalar matches no schema under jit.trace)
    except (IndexError, RuntimeError):
        # a NaN location becomes cell INT64_MIN (every valid cell is >= 0): say what is wrong, not the index
        if bool((c00 < 0).any()):
            raise MSSFError(
                "sampling locations: expected finite values, got NaN: the queries (e.g. voxel features) or the "
                "weights of the layers computing the sampling offsets are not finite") from None
        raise
    mark = mark.view(num_images, hp, wp)
    return (mark[:, 2 : h + 2, 2 : w + 2] | mark[:, 2 : h + 2, 1 : w + 1]).logical_or_(
        mark[:, 1 : h + 1, 2 : w + 2] | mark[:, 1 : h + 1, 1 : w + 1])


# ---------------------------------------------------------------------------------------------------
# the level's raw rows: a (pixels, D) row table, the touched rows gathered in cache-sized pieces, and
# their projection (an autograd function that gathers them again for the weight gradient)
# ---------------------------------------------------------------------------------------------------
def _row_table(value: Tensor) -> Optional[Tensor]:
    """``value (I, 1, D, H, W)`` as a free ``(I * H * W, D)`` table with contiguous rows, or ``None``.

    Only channels-last memory qualifies: an NCHW map also has an ``(I * H * W, D)`` view (for
    ``I = 1``), but with stride ``H * W`` along ``D``, i.e. every row scattered over ``D`` planes.
    """
    try:
        table = value.permute(0, 1, 3, 4, 2).view(-1, value.shape[2])
    except RuntimeError:
        return None
    return table if table.stride(1) == 1 or table.shape[1] == 1 else None


def _is_row_table(value: Tensor) -> bool:
    return _row_table(value) is not None


def _touched_rows(value: Tensor, touched: Tensor, chunk: int) -> Iterator[Tensor]:
    """Raw rows of the sorted flat pixel ids ``touched`` of ``value (I, 1, D, H, W)``, as ``(<= chunk, D)``
    pieces in order, gathered one at a time (a consumer that drops each piece keeps one in memory).

    Channels-last maps are one ``(I * H * W, D)`` row table (contiguous pieces). NCHW maps are read
    plane by plane: each channel's ``H * W`` plane at the sorted pixel ids (short forward strides)
    into a ``(D, n)`` block, yielded as its transposed ``(n, D)`` view, which a GEMM reads in place
    (measured 30 % faster than gathering rows of the transposed ``(H * W, D)`` view, 10^4-10^5 of the
    147,136 pixels of a 256-channel P2). Pieces of ``chunk`` sorted pixels keep the reads of every
    channel plane within a narrow band (measured 2x faster than one gather over a whole 10^5-pixel
    level) and, when consumed right away (e.g. by a GEMM), are still in cache.
    """
    num_images, _, dch, h, w = value.shape
    table = _row_table(value)
    if table is not None:
        # (an empty piece when nothing is touched keeps the image in the graph: zero gradient, not None)
        for s in range(0, max(touched.numel(), 1), chunk):
            yield table.index_select(0, touched[s : s + chunk])
        return
    bounds = torch.searchsorted(
        touched, torch.arange(num_images + 1, device=touched.device, dtype=touched.dtype) * (h * w)
    ).tolist()
    if bounds[-1] == 0:
        yield value[0, 0].reshape(dch, h * w).index_select(1, touched).t()
    for i in range(num_images):
        planes = value[i, 0].reshape(dch, h * w)  # (D, H*W): one contiguous plane per channel
        for s in range(bounds[i], bounds[i + 1], chunk):
            yield planes.index_select(1, touched[s : min(s + chunk, bounds[i + 1])] - i * h * w).t()


def _gather_rows(value: Tensor, touched: Tensor) -> Tensor:
    """``(U, D)`` contiguous table of the raw rows of the sorted pixel ids ``touched`` (``U >= 1``),
    gathered piece by piece straight into it (no second copy) unless autograd must see the gather."""
    if value.requires_grad and torch.is_grad_enabled():
        parts = list(_touched_rows(value, touched, _PROJECT_CHUNK))
        return parts[0].contiguous() if len(parts) == 1 else torch.cat(parts, 0)
    table = value.new_empty(touched.numel(), value.shape[2])
    start = 0
    for piece in _touched_rows(value, touched, _PROJECT_CHUNK):
        table[start : start + piece.shape[0]] = piece
        start += piece.shape[0]
    return table


def _project_rows(value: Tensor, w_all: Tensor, b_all: Optional[Tensor], touched: Optional[Tensor],
                  out: Optional[Tensor] = None):
    """``(rows, E)`` projection, in pieces, of every pixel of ``value (I, 1, D, H, W)`` (``touched=None``:
    sequential reads, one GEMM per image) or of the sorted pixel ids ``touched`` only (gathered in
    cache-sized pieces, each projected at once and dropped). Returns the list of pieces, or, with
    ``out`` (no autograd: ``out=`` GEMMs), writes them into its first rows and returns ``out``."""
    if touched is None:
        dch, h, w = value.shape[2:]
        raws = (value[i, 0].reshape(dch, h * w).t() for i in range(value.shape[0]))  # transposed views for NCHW
    else:
        raws = _touched_rows(value, touched, _PROJECT_CHUNK)
    if out is None:
        return [raw @ w_all.t() if b_all is None else torch.addmm(b_all, raw, w_all.t()) for raw in raws]
    start = 0
    for raw in raws:
        dst = out[start : start + raw.shape[0]]
        if b_all is None:
            torch.mm(raw, w_all.t(), out=dst)
        else:
            torch.addmm(b_all, raw, w_all.t(), out=dst)
        start += raw.shape[0]
    return out


class _GatherProject(torch.autograd.Function):
    """``(U, E)`` projection ``rows @ weight.T + bias`` of the touched raw rows of ``value (I, 1, D, H, W)``
    (sorted flat pixel ids ``touched``) that does not keep the gathered ``(U, D)`` rows for backward:
    the weight gradient gathers them again, piece by piece (one more gather instead of ``U * D``
    saved elements, e.g. 53 MiB for 35 % of a 256-channel P2)."""

    @staticmethod
    def forward(ctx, value: Tensor, touched: Tensor, weight: Tensor, bias: Optional[Tensor]) -> Tensor:
        ctx.save_for_backward(value, touched, weight)
        ctx.has_bias = bias is not None
        return _project_rows(value, weight, bias, touched, out=weight.new_empty(touched.numel(), weight.shape[0]))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: Tensor):
        value, touched, weight = ctx.saved_tensors
        grad_value = grad_weight = grad_bias = None
        if ctx.needs_input_grad[2]:
            grad_weight = torch.zeros_like(weight)
            start = 0
            for raw in _touched_rows(value, touched, _PROJECT_CHUNK):
                grad_weight.addmm_(grad[start : start + raw.shape[0]].t(), raw)
                start += raw.shape[0]
        if ctx.has_bias and ctx.needs_input_grad[3]:
            grad_bias = grad.sum(0)
        if ctx.needs_input_grad[0]:
            num_images, _, dch, h, w = value.shape
            rows = value.new_zeros(num_images * h * w, dch).index_add_(0, touched, grad @ weight)
            grad_value = rows.view(num_images, h, w, 1, dch).permute(0, 3, 4, 1, 2)
        return grad_value, None, grad_weight, grad_bias


def _grid_sample_heads(maps: Tensor, image_index: Tensor, loc: Tensor, wt: Tensor) -> Tensor:
    """``(M * Q, d)`` head-major ``sum_p wt * bilinear(maps[image, :, :, m], loc)`` with ``F.grid_sample``.

    ``maps (I, H, W, M, d)`` (a projected level, e.g. a view of ``(I * H * W, M * d)`` rows),
    ``loc (Q, M, P, 2)`` normalised, ``wt (Q, M, P)``. Zero padding, ``align_corners=False``: the
    arithmetic of :func:`ms_deform_sample_reference`, laid out head-major (no per-image gather and
    index_add for one image). Calling the reference instead gives the same values up to rounding, but
    not bit for bit, and the demo's 2000 training steps amplify that (+13.42 -> +14.33 mAP).
    """
    num_images, _, _, m, d = maps.shape
    q = loc.shape[0]
    heads = maps.permute(0, 3, 4, 1, 2)  # (I, M, d, H, W) view: grid_sample reads any strides
    grid = (2.0 * loc - 1.0).transpose(0, 1)  # (M, Q, P, 2)
    wo = wt.transpose(0, 1)[:, None]  # (M, 1, Q, P)

    def sample(i: int, g: Tensor, w: Tensor) -> Tensor:  # (M, d, q_i, P) -> (M, q_i, d)
        s = F.grid_sample(heads[i], g, mode="bilinear", padding_mode="zeros", align_corners=False)
        return (s * w).sum(-1).transpose(1, 2)

    if num_images == 1:
        return sample(0, grid, wo).reshape(m * q, d)
    out = maps.new_zeros(m, q, d)
    for i in range(num_images):
        sel = (image_index == i).nonzero().squeeze(1)
        if sel.numel():
            out = out.index_copy(1, sel, sample(i, grid[:, sel], wo[:, :, sel]))
    return out.view(m * q, d)

def _touched_level(
    value: Tensor,
    image_index: Tensor,
    lv: _LevelLoc,
    w_all: Optional[Tensor],
    b_all: Optional[Tensor],
    m: int,
    plan: Optional[str],
    needs_grad: bool = False,
    defer_projection: bool = False,
    projection_paid: bool = False,
):
    """One level of the ``"touched"`` method: ``(Q, M, d)`` output (possibly a strided view).

    With ``defer_projection``, the raw-row plans return a :class:`_RawLevel` instead, for the caller to
    bag with the other levels in blocks of queries and project each block once (``value_proj`` is
    shared by the levels: one per-head ``bmm`` per block instead of one per level), and in forward the
    projected plans return a :class:`_ProjectedLevel` (their table made, their corners left to the
    caller's blocks);
    ``projection_paid``: an earlier level already did, so the raw-row plans' cost leaves that
    projection out.

    With ``w_all=None`` (no projection; used by :func:`bilinear_sample`) the plan is ``"sample"`` (or
    the given raw-row plan, ``"direct"`` for a channels-last map) and the raw ``(Q * M, D)`` bilinear
    samples are returned.

    ``value (I, 1, D, H, W)``, ``lv`` the level's points (:func:`_level`; ``lv.loc`` and
    ``lv.wt`` are needed with ``needs_grad``), ``w_all (M * d, D)``, ``b_all (M * d,)``. Corners are
    located on the level padded by 2 pixels on every side, with the
    top-left corner clamped to ``[-2, W]`` x ``[-2, H]``: every corner then has a cell of the padded
    grid, and a corner is in the map iff its cell is not in the padding (no per-corner masks). The
    top-left cells are marked in a ``(I, H + 4, W + 4)`` array and the pixels read by some corner are
    those with a marked cell at offset ``(0, 0)``, ``(0, -1)``, ``(-1, 0)`` or ``(-1, -1)``
    (O(pixels + points), no sort); the touched in-map pixels are projected with one GEMM (all heads at
    once) into a ``(U + 1, M * d)`` table whose last row is zero and which padding cells map to
    (grid_sample's zero padding, bias included); every corner then reads its head's ``d`` channels of
    its row in one ``embedding_bag`` weighted by ``bilinear weight * attention weight``.

    With ``needs_grad`` the plan costs include the backward pass, and the projected plans sample with
    ``F.grid_sample`` from a dense projected map instead (touched rows scattered into zeros for
    ``"project"``): its fused backward is several times cheaper than ``embedding_bag``'s (per-corner
    weight gradients and a sorted table gradient).
    """
    num_images, _, dch, h, w = value.shape
    q, _, p = lv.x.shape
    e = dch * m if w_all is None else w_all.shape[0]
    d = e // m
    dev = value.device
    n_pix = num_images * h * w
    if w_all is None:
        plan = "sample" if plan is None else plan
    hp, wp = h + 4, w + 4
    n_cells = num_images * hp * wp
    c00 = _top_left_cells(lv, image_index, num_images, h, w)  # (Q, M, P)
    # int32 corner cells while the cells with the head folded in (below) fit: half the bytes to write
    # and read (measured 4-7 % of the whole call, 2,500-8,000 queries)
    cdt = torch.int32 if m * n_cells < 2**31 else torch.int64

    # Which in-map pixels are read (the plans "project" and "sample" need them; the choice needs
    # their number U), as raw pixel ids (image, y, x) -> (i * H + y) * W + x.
    inner, u = None, n_pix
    if plan is None or plan in ("project", "sample") or (needs_grad and plan == "dense"):
        inner = _read_pixels(c00, num_images, h, w)
        u = int(inner.sum())
    if plan is None:
        corners = m * q * 4 * p
        bag = 1.0 + _BAG_BACKWARD if needs_grad else 1.0  # forward (+ backward) passes over the corners
        gemm = 2.0 if needs_grad else 1.0  # the projection (+ its weight gradient)
        # the projected plans' sampling: d channels per head and corner (per input channel: / D)
        read = corners * d / dch * (_GRID_SAMPLE_COST if needs_grad else _BAG_COST)
        # the raw-row plans' per-head projection, shared by the levels that take one (deferred)
        raw_projection = 0.0 if projection_paid else q * e * gemm
        costs = {
            "dense": n_pix * e * gemm + read,
            # (with gradients the touched rows are gathered again for the weight gradient)
            "project": u * (e + _GATHER_COST) * gemm + (n_pix * e * _FILL_COST if needs_grad else 0.0) + read,
            "sample": u * (_GATHER_COST + _COPY_COST) + corners * _BAG_COST * bag + raw_projection,
        }
        if _is_row_table(value):
            costs["direct"] = corners * _DIRECT_BAG_COST * bag + raw_projection
        plan = min(costs, key=costs.get)
    touched = inner.view(-1).nonzero().squeeze(1) if plan in ("project", "sample") else None  # (U,) sorted
    if needs_grad and plan in ("dense", "project"):
        # Project (every pixel, or the touched ones scattered into zeros: untouched pixels are never
        # read, weight-0 corners included), then grid_sample per head: its fused backward is several
        # times cheaper than embedding_bag's.
        if plan == "dense":
            parts = _project_rows(value, w_all, b_all, None)
            if u < n_pix and not all(bool(torch.isfinite(part).all()) for part in parts):
                # A NaN / inf in a pixel no corner reads never reaches the output, but it would reach
                # value_proj's weight gradient (0 * NaN): project again with such pixels zeroed. Only then:
                # the check reads the (pixels, E) projection once (measured ~15 % of one projection GEMM
                # at E = 64), the masked copy of the level would cost more than the GEMM itself.
                src = torch.where(inner.view(num_images, 1, 1, h, w), value, 0.0)
                parts = _project_rows(src, w_all, b_all, None)
            projected = parts[0] if len(parts) == 1 else torch.cat(parts, 0)
        else:
            projected = _GatherProject.apply(value, touched, w_all, b_all)
            projected = projected.new_zeros(n_pix, e).index_copy(0, touched, projected)
        heads = _grid_sample_heads(projected.view(num_images, h, w, m, d), image_index, lv.loc, lv.wt)
        return heads.view(m, q, d).transpose(0, 1)
    n_rows = n_pix if plan in ("dense", "direct") else u
    idt = torch.int32 if (n_rows + 1) * m < 2**31 else torch.int64
    remap = torch.full((num_images, hp, wp), n_rows, dtype=idt, device=dev)  # padding: the zero row
    if plan in ("dense", "direct"):  # every pixel has a row: its raw pixel id
        remap[:, 2 : h + 2, 2 : w + 2] = torch.arange(n_pix, dtype=idt, device=dev).view(num_images, h, w)
    else:  # the touched pixels' rows, in order
        remap[:, 2 : h + 2, 2 : w + 2].masked_scatter_(inner, torch.arange(u, dtype=idt, device=dev))
    if plan in ("sample", "direct"):
        # Sample the D raw channels per head and point from the level's rows (channels-last maps are a
        # free (I * H * W, D) row table: sampled in place) or from a compact table of the touched rows,
        # then project per head (Q * D * E) and add the bias times the in-map weight mass. No zero row
        # here (appending one would copy the table): out-of-map corners get weight 0 and the last row,
        # or, should that row not be finite, are left out of their bags (_bag_raw).
        table = _row_table(value) if plan == "direct" else _gather_rows(value, touched)
        if n_rows == 0:  # (the empty table keeps the image in the graph: zero gradient, not None)
            table, clamp = value.new_zeros(1, dch) + 0.0 * table.sum(), 0  # (every cell maps to its row 0)
        else:
            clamp = n_rows - 1 if bool(torch.isfinite(table[n_rows - 1]).all()) else None
        raw = _RawLevel(lv, c00.to(cdt), remap.view(-1), wp, table, n_rows, clamp)
        if defer_projection and w_all is not None:
            return raw  # the caller bags it with the other levels, in blocks of queries
        sampled, mass = _bag_raw(raw, 0, q)  # (Q * M, D), (Q, M, 1)
        if w_all is None:
            return sampled
        out = torch.bmm(sampled.view(q, m, dch).transpose(0, 1), w_all.view(m, d, dch).transpose(1, 2))
        out = out.transpose(0, 1)  # (Q, M, d)
        return out if b_all is None else out + mass * b_all.view(1, m, d)
    # (forward only: with gradients these plans returned above) one (rows + 1, E) table whose last row,
    # the one padding cells read, is zero, viewed ((rows + 1) * M, d): row r * M + head. The head is
    # folded into the cells (one table of cell -> row per head) rather than added to every corner's row.
    table = w_all.new_empty(n_rows + 1, e)
    table[n_rows].zero_()
    _project_rows(value, w_all, b_all, None if plan == "dense" else touched, out=table[:n_rows])
    heads = torch.arange(m, dtype=idt, device=dev)
    remap = torch.addcmul(heads.view(m, 1), remap.view(1, -1), heads.new_full((), m))  # (M, cells): r * M + head
    c00 = c00.add_((heads.long() * n_cells).view(1, m, 1)).to(cdt)
    level = _ProjectedLevel(lv, c00, remap.view(-1), wp, table.view(-1, d))
    return level if defer_projection else _bag_projected(level, 0, q)
