"""The embedding-bag path of ``ms_deform_sample`` (any ``Mv``, no projection): the four bilinear corners
of every point as rows of each level's ``(pixels, D)`` table, reduced by ``embedding_bag(mode="sum")``
weighted by ``bilinear weight * attention weight`` (never a gathered ``(corners, D)`` tensor); autograd
carries the per-corner weight gradient back to ``locations`` and ``weights``. Inputs unchecked (the
public functions check them)."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from mssf_blocks import torch_versions
from mssf_blocks.functional.deform.touched.order import _inverse
from mssf_blocks.functional.deform.touched.points import _pixel_coordinate
from mssf_blocks.functional.plan_costs import _STATIC_BAG_COST

__all__ = ["STATIC_PLAN_QUERIES", "plan_queries", "sample", "sample_project_chunked", "sample_project_static"]


def _index_dtype(values: Sequence[Tensor], mv: int) -> torch.dtype:
    # int32 rows halve the index memory and are read natively by embedding_bag.
    rows = max(v.shape[0] * mv * v.shape[-2] * v.shape[-1] for v in values)
    return torch.int32 if rows + 2 * max(v.shape[-1] for v in values) < 2**31 else torch.int64


def sample(
    values: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor, return_mass: bool,
    query_major: bool = False,
) -> Union[Tensor, Tuple[Tensor, Tensor]]:
    q, m, num_levels, p, _ = locations.shape
    mv, d = values[0].shape[1:3]
    dev = locations.device
    # Work level-major and head-major, (L, M, Q, P): every level's corners are a contiguous slice and
    # the embedding-bag output comes out as (M, Q, D), the layout a per-head projection (bmm) wants.
    # With query_major, (L, Q, M, P) instead: the bags of a query's heads are neighbours, and read rows
    # near the same reference point while they are in cache (the static path: 0.88-0.94 of the time,
    # benchmarks/static_path.py's MSDFF cases); the output is then (Q, M, D) memory.
    order = (2, 0, 1) if query_major else (2, 1, 0)
    locs = locations.permute(*order, 3, 4)
    wts = weights.permute(*order, 3)
    hs = torch.tensor([v.shape[-2] for v in values], device=dev).view(num_levels, 1, 1, 1)
    ws = torch.tensor([v.shape[-1] for v in values], device=dev).view(num_levels, 1, 1, 1)
    size_w = ws.to(locations.dtype)
    size_h = hs.to(locations.dtype)
    x = _pixel_coordinate(locs[..., 0], size_w)  # (L, M, Q, P)
    y = _pixel_coordinate(locs[..., 1], size_h)
    x0 = x.detach().floor()
    y0 = y.detach().floor()
    fx = x - x0  # carries d/dx; floor is piecewise constant
    fy = y - y0
    # Per-axis corner weights, zero where the corner is outside the map (zero padding); the attention
    # weight is folded into the y factors so that each corner weight is one product.
    ax0 = (1.0 - fx) * ((x0 >= 0) & (x0 <= size_w - 1))
    ax1 = fx * ((x0 >= -1) & (x0 <= size_w - 2))
    ay0 = (1.0 - fy) * ((y0 >= 0) & (y0 <= size_h - 1)) * wts
    ay1 = fy * ((y0 >= -1) & (y0 <= size_h - 2)) * wts
    # Corner-major inside each (head, query) bag, (L, M, Q, 4, P): the order within a bag is free and
    # this layout stacks in blocks of P instead of interleaving single elements.
    psw = torch.stack((ay0 * ax0, ay0 * ax1, ay1 * ax0, ay1 * ax1), -2)  # (L, M, Q, 4, P)
    mass = None
    if return_mass:
        mass = ((ay0 + ay1) * (ax0 + ax1)).sum((0, 3))
        mass = mass if query_major else mass.t()  # (Q, M)

    # Row of the top-left corner in level l's table (I * Mv * H_l * W_l, D):
    #   ((image * Mv + head) * H_l + y0) * W_l + x0, computed on points (4x fewer than corners) after
    # clamping x0, y0 to [-1, size] so that huge coordinates cannot overflow; the corners add
    # (0, 1, W_l, W_l + 1). A corner outside the map has weight 0 and any row inside the table will
    # do, hence the final clamp to the table.
    idt = _index_dtype(values, mv)
    heads = torch.arange(m, device=dev, dtype=idt)[:, None] if mv > 1 else torch.zeros((m, 1), dtype=idt, device=dev)
    plane = image_index.to(idt)[None, :] * mv + heads  # (M, Q)
    plane = plane.t().reshape(1, q, m, 1) if query_major else plane.view(1, m, q, 1)
    x0i = torch.minimum(x0.clamp(min=-1.0), size_w).to(idt)
    y0i = torch.minimum(y0.clamp(min=-1.0), size_h).to(idt)
    hs_i, ws_i = hs.to(idt), ws.to(idt)
    base = (plane * hs_i + y0i) * ws_i + x0i  # (L, M, Q, P)
    corner_offsets = torch.stack([torch.zeros_like(ws_i), torch.ones_like(ws_i), ws_i, ws_i + 1], -2)  # (L,1,1,4,1)
    last_row = torch.tensor(
        [v.shape[0] * mv * v.shape[-2] * v.shape[-1] - 1 for v in values], device=dev, dtype=idt
    ).view(num_levels, 1, 1, 1, 1)
    rows = torch.clamp(base[..., None, :] + corner_offsets, min=torch.zeros_like(last_row), max=last_row)

    out = None
    for lvl, val in enumerate(values):
        # (I, Mv, D, H, W) -> (I * Mv * H * W, D): a free view for channels-last features (stride 1
        # along D); otherwise one layout copy of this level.
        table = val.permute(0, 1, 3, 4, 2).reshape(-1, d)
        if table.stride(-1) != 1:  # (embedding_bag reads a strided table several times slower than a copy)
            table = table.contiguous()
        part = torch_versions.embedding_bag(
            rows[lvl].reshape(m * q, p * 4), table, per_sample_weights=psw[lvl].reshape(m * q, p * 4), mode="sum"
        )  # (M * Q, D)
        if out is None:
            out = part
        else:
            out += part  # in place: embedding_bag's backward does not need its output
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
    each bag's sum is the same in any order.
    """
    q, m, _, p, _ = locations.shape
    d = proj_weight.shape[1]
    sizes = [tuple(lvl.shape[-2:]) for lvl in levels]
    order = _row_order(image_index, locations, sizes)
    image_index, locations, weights = image_index[order], locations[order], weights[order]
    dense = [_dense_pays(lvl, q, m, p, d) for lvl in levels]
    out = None
    raw = [i for i, dn in enumerate(dense) if not dn]
    if raw:
        sampled, mass = sample([levels[i] for i in raw], image_index, locations[:, :, raw], weights[:, :, raw], True,
                               query_major=True)
        out = torch.bmm(sampled.transpose(0, 1), proj_weight.transpose(1, 2)).transpose(0, 1)  # (Q, M, d)
        out = out + mass[..., None] * proj_bias
    projected = [i for i, dn in enumerate(dense) if dn]
    if projected:
        values = [_project_level(levels[i], proj_weight, proj_bias) for i in projected]
        part = sample(values, image_index, locations[:, :, projected], weights[:, :, projected], False,
                      query_major=True)
        out = part if out is None else out + part
    return out[_inverse(order)]


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
