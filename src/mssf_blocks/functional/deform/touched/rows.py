"""Raw rows of a level for the CPU plans: the level as a ``(pixels, D)`` row table, the touched pixels'
rows gathered in cache-sized pieces, and their projection (with an autograd function that gathers
them again for the weight gradient instead of keeping them)."""

from __future__ import annotations

from typing import Iterator, Optional

import torch
from torch import Tensor

from ...plan_costs import _PROJECT_CHUNK

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

