"""Triton kernels of multi-scale deformable sampling (the CUDA backend of the sampling op).

Imported lazily (only when the op's ``"triton"`` backend runs, or by the tests): ``import
mssf_blocks`` never imports ``triton``. The kernels read a flat value buffer, every level's projected
pixels one after the other, laid out like mmcv's multi-scale deformable attention::

    value (I, S, M, d)    S = sum_l H_l * W_l, level l's pixel (y, x) at row start_l + y * W_l + x

Conventions (``docs/conventions.md``): location ``(u, v)`` is normalised to the image, the pixel
coordinate on level ``l`` is ``x = u * W_l - 0.5`` (pixel ``i``'s centre at ``u = (i + 0.5) / W_l``),
bilinear with zero padding: a corner outside the map reads zero, never a clamped edge pixel.

* forward: one program per block of ``BLOCK_Q`` queries and one head; per level and point the four
  corners are read with masked loads, the ``d`` channels accumulated in float32 registers, one write
  of ``(BLOCK_Q, d)``. No ``(Q, ..., d)`` intermediate.
* backward: the same loop; the value gradient by atomic adds into a float32 buffer (compiled out when
  the value needs no gradient), the location and attention-weight gradients written once per
  (query, head, level, point).

Every machine-dependent choice (block sizes, warps) is in :func:`launch_config`, measured by the
ahead-of-time compile test (``tests/functional/test_triton_compile.py``: no register spills on sm_80
and sm_90).
"""

from __future__ import annotations

import os
from typing import Optional, Tuple

import torch
from torch import Tensor

# Fused multiply-adds change the last bits; fixed explicitly (its default changes in Triton 3.10): set
# before triton is imported, and passed to every launch and compile (FP_FUSION).
os.environ.setdefault("TRITON_DEFAULT_FP_FUSION", "1")
FP_FUSION = True

import triton  # noqa: E402
import triton.language as tl  # noqa: E402

__all__ = ["deform_sample_forward", "deform_sample_backward", "launch_config", "forward_kernel", "backward_kernel"]


@triton.jit
def _corner(value_ptr, head_off, row_base, x0, y0, fx, fy, w_l, h_l, cols, col_mask, qmask,
            CORNER: tl.constexpr, M: tl.constexpr, D: tl.constexpr):
    """Bilinear corner ``CORNER`` (0-3: ``x0 + CORNER % 2``, ``y0 + CORNER // 2``) of a block of points:
    its weights along x and y, its ``(BLOCK_Q, BLOCK_D)`` values in float32 (zero outside the map), and
    their offsets into ``value`` and mask."""
    cx = x0 + CORNER % 2
    cy = y0 + CORNER // 2
    wx = fx if CORNER % 2 == 1 else 1.0 - fx
    wy = fy if CORNER // 2 == 1 else 1.0 - fy
    inside = qmask & (cx >= 0) & (cx < w_l) & (cy >= 0) & (cy < h_l)
    row = row_base + (cy * w_l + cx).to(tl.int64)  # (BLOCK_Q,) pixel row of (image, level)
    offs = (row * M)[:, None] * D + head_off + cols[None, :]
    mask = inside[:, None] & col_mask[None, :]
    return wx, wy, tl.load(value_ptr + offs, mask=mask, other=0.0).to(tl.float32), offs, mask


@triton.jit
def _block(index_ptr, Q, D: tl.constexpr, BLOCK_Q: tl.constexpr, BLOCK_D: tl.constexpr):
    """The program's block of queries and the head's channels: ``(q64, qmask, cols, col_mask, img)``."""
    qs = tl.program_id(0) * BLOCK_Q + tl.arange(0, BLOCK_Q)
    qmask = qs < Q
    cols = tl.arange(0, BLOCK_D)
    img = tl.load(index_ptr + qs, mask=qmask, other=0).to(tl.int64)
    return qs.to(tl.int64), qmask, cols, cols < D, img


@triton.jit
def _level(shapes_ptr, starts_ptr, img, S, lvl):
    """Level ``lvl``'s ``(h_l, w_l)`` and the row of its first pixel in every query's image."""
    h_l = tl.load(shapes_ptr + 2 * lvl)
    w_l = tl.load(shapes_ptr + 2 * lvl + 1)
    start = tl.load(starts_ptr + lvl).to(tl.int64)
    return h_l, w_l, img * S + start


@triton.jit
def _point(loc_ptr, wt_ptr, q64, qmask, m, lvl, pt, h_l, w_l,
           loc_sq, loc_sm, loc_sl, loc_sp, loc_sc, wt_sq, wt_sm, wt_sl, wt_sp):
    """One sampling point of a block of queries: its attention weight, the fractions ``fx, fy`` of its
    pixel coordinates and its top-left corner ``x0, y0``."""
    loc_off = q64 * loc_sq + m * loc_sm + lvl * loc_sl + pt * loc_sp
    u = tl.load(loc_ptr + loc_off, mask=qmask, other=0.0).to(tl.float32)
    v = tl.load(loc_ptr + loc_off + loc_sc, mask=qmask, other=0.0).to(tl.float32)
    aw = tl.load(wt_ptr + q64 * wt_sq + m * wt_sm + lvl * wt_sl + pt * wt_sp, mask=qmask, other=0.0).to(tl.float32)
    # pixel coordinates, clamped to [-2, size + 1] (same corners, no integer overflow)
    x = tl.minimum(tl.maximum(u * w_l - 0.5, -2.0), w_l + 1.0)
    y = tl.minimum(tl.maximum(v * h_l - 0.5, -2.0), h_l + 1.0)
    xf = tl.floor(x)
    yf = tl.floor(y)
    return aw, x - xf, y - yf, xf.to(tl.int32), yf.to(tl.int32)


@triton.jit
def forward_kernel(
    value_ptr, shapes_ptr, starts_ptr, index_ptr, loc_ptr, wt_ptr, out_ptr,
    Q, S,
    loc_sq, loc_sm, loc_sl, loc_sp, loc_sc,
    wt_sq, wt_sm, wt_sl, wt_sp,
    L, P,
    M: tl.constexpr, D: tl.constexpr,
    BLOCK_Q: tl.constexpr, BLOCK_D: tl.constexpr,
):
    m = tl.program_id(1)
    q64, qmask, cols, col_mask, img = _block(index_ptr, Q, D, BLOCK_Q, BLOCK_D)
    acc = tl.zeros((BLOCK_Q, BLOCK_D), dtype=tl.float32)
    head_off = m * D
    for lvl in range(L):
        h_l, w_l, row_base = _level(shapes_ptr, starts_ptr, img, S, lvl)
        for pt in range(P):
            aw, fx, fy, x0, y0 = _point(loc_ptr, wt_ptr, q64, qmask, m, lvl, pt, h_l, w_l, loc_sq, loc_sm, loc_sl,
                                        loc_sp, loc_sc, wt_sq, wt_sm, wt_sl, wt_sp)
            for corner in tl.static_range(4):
                wx, wy, val, _, _ = _corner(value_ptr, head_off, row_base, x0, y0, fx, fy, w_l, h_l, cols, col_mask,
                                            qmask, corner, M, D)
                acc += (aw * wx * wy)[:, None] * val
    out_offs = ((q64 * M + m) * D)[:, None] + cols[None, :]
    tl.store(out_ptr + out_offs, acc.to(out_ptr.dtype.element_ty), mask=qmask[:, None] & col_mask[None, :])


@triton.jit
def backward_kernel(
    value_ptr, shapes_ptr, starts_ptr, index_ptr, loc_ptr, wt_ptr, grad_out_ptr,
    grad_value_ptr, grad_loc_ptr, grad_wt_ptr,
    Q, S,
    loc_sq, loc_sm, loc_sl, loc_sp, loc_sc,
    wt_sq, wt_sm, wt_sl, wt_sp,
    L, P,
    M: tl.constexpr, D: tl.constexpr,
    BLOCK_Q: tl.constexpr, BLOCK_D: tl.constexpr, VALUE_GRAD: tl.constexpr,
):
    """Gradients of :func:`forward_kernel`; ``grad_loc (Q, M, L, P, 2)`` and ``grad_wt (Q, M, L, P)``
    contiguous float32, ``grad_value`` a float32 buffer shaped like ``value`` (unused unless
    ``VALUE_GRAD``)."""
    m = tl.program_id(1)
    q64, qmask, cols, col_mask, img = _block(index_ptr, Q, D, BLOCK_Q, BLOCK_D)
    g_offs = ((q64 * M + m) * D)[:, None] + cols[None, :]
    g = tl.load(grad_out_ptr + g_offs, mask=qmask[:, None] & col_mask[None, :], other=0.0).to(tl.float32)
    head_off = m * D
    for lvl in range(L):
        h_l, w_l, row_base = _level(shapes_ptr, starts_ptr, img, S, lvl)
        for pt in range(P):
            aw, fx, fy, x0, y0 = _point(loc_ptr, wt_ptr, q64, qmask, m, lvl, pt, h_l, w_l, loc_sq, loc_sm, loc_sl,
                                        loc_sp, loc_sc, wt_sq, wt_sm, wt_sl, wt_sp)
            sampled = tl.zeros((BLOCK_Q,), dtype=tl.float32)  # <g, bilinear sample>
            gx = tl.zeros((BLOCK_Q,), dtype=tl.float32)  # <g, d sample / d fx>
            gy = tl.zeros((BLOCK_Q,), dtype=tl.float32)
            for corner in tl.static_range(4):
                wx, wy, val, offs, mask = _corner(value_ptr, head_off, row_base, x0, y0, fx, fy, w_l, h_l, cols,
                                                  col_mask, qmask, corner, M, D)
                sx = 1.0 if corner % 2 == 1 else -1.0  # d wx / d fx
                sy = 1.0 if corner // 2 == 1 else -1.0
                dot = tl.sum(val * g, axis=1)
                sampled += wx * wy * dot
                gx += sx * wy * dot
                gy += sy * wx * dot
                if VALUE_GRAD:
                    tl.atomic_add(grad_value_ptr + offs, (aw * wx * wy)[:, None] * g, mask=mask)
            out_off = ((q64 * M + m) * L + lvl) * P + pt
            tl.store(grad_wt_ptr + out_off, sampled, mask=qmask)
            tl.store(grad_loc_ptr + 2 * out_off, aw * gx * w_l, mask=qmask)
            tl.store(grad_loc_ptr + 2 * out_off + 1, aw * gy * h_l, mask=qmask)


# ---------------------------------------------------------------------------------------------------
# launch
# ---------------------------------------------------------------------------------------------------
def launch_config(d: int, backward: bool) -> Tuple[int, int, int]:
    """``(BLOCK_Q, BLOCK_D, num_warps)`` for ``d`` channels per head (``d <= 256``, the op's
    ``TRITON_MAX_HEAD_DIM``).

    1,024 elements of the ``(BLOCK_Q, BLOCK_D)`` tile over 8 warps (4 per thread): measured with
    ``tests/functional/triton_aot.py`` (``ptxas -v`` of the sm_80 compile, float32), the forward at
    d = 32 used 128 registers and the backward 220, no spills; 8 elements per thread (4 warps) took
    the forward to 239 registers and spilled the backward (52 bytes); 16 per thread (block 64 x 32,
    4 warps) spilled both (1.2 / 1.7 KB). The compile test asserts no spill for every variant on
    sm_80 and sm_90. Not yet timed on a GPU (``benchmarks/gpu_check.py``).
    """
    block_d = triton.next_power_of_2(max(int(d), 1))
    block_q = max(1, min(64, 1024 // block_d))
    return block_q, block_d, 8


def _flat_args(loc: Tensor, wt: Tensor):
    return (*loc.stride(), *wt.stride())


def deform_sample_forward(
    value: Tensor, shapes: Tensor, starts: Tensor, image_index: Tensor, locations: Tensor, weights: Tensor,
    block_q: Optional[int] = None,
) -> Tensor:
    """``(Q, M, d)`` in ``value``'s dtype; ``value (I, S, M, d)`` contiguous, ``shapes (L, 2)`` int32
    ``(H_l, W_l)``, ``starts (L,)`` int32, ``image_index (Q,)``, ``locations (Q, M, L, P, 2)`` and
    ``weights (Q, M, L, P)`` with any strides. No validation (the op checks at its entry)."""
    q, m, num_levels, p, _ = locations.shape
    num_images, s, _, d = value.shape
    value = value.contiguous()  # (a no-op for the op's buffer; the kernels read (I, S, M, d) rows)
    out = value.new_empty(q, m, d)
    if q == 0:
        return out
    bq, bd, warps = launch_config(d, backward=False)
    bq = block_q or bq
    grid = (triton.cdiv(q, bq), m)
    forward_kernel[grid](
        value, shapes, starts, image_index.contiguous(), locations, weights, out, q, s, *_flat_args(locations, weights),
        num_levels, p, M=m, D=d, BLOCK_Q=bq, BLOCK_D=bd, num_warps=warps, enable_fp_fusion=FP_FUSION,
    )
    return out


def deform_sample_backward(
    value: Tensor, shapes: Tensor, starts: Tensor, image_index: Tensor, locations: Tensor, weights: Tensor,
    grad_out: Tensor, value_grad: bool, block_q: Optional[int] = None,
) -> Tuple[Optional[Tensor], Tensor, Tensor]:
    """``(grad_value or None, grad_locations, grad_weights)``, each in its input's dtype."""
    q, m, num_levels, p, _ = locations.shape
    d = value.shape[-1]
    value = value.contiguous()
    grad_loc = torch.zeros(q, m, num_levels, p, 2, device=value.device, dtype=torch.float32)
    grad_wt = torch.zeros(q, m, num_levels, p, device=value.device, dtype=torch.float32)
    grad_value = torch.zeros(value.shape, device=value.device, dtype=torch.float32) if value_grad else None
    if q:
        bq, bd, warps = launch_config(d, backward=True)
        bq = block_q or bq
        grid = (triton.cdiv(q, bq), m)
        backward_kernel[grid](
            value, shapes, starts, image_index.contiguous(), locations, weights, grad_out.contiguous(),
            grad_value if value_grad else grad_wt, grad_loc, grad_wt, q, value.shape[1],
            *_flat_args(locations, weights),
            num_levels, p, M=m, D=d, BLOCK_Q=bq, BLOCK_D=bd, VALUE_GRAD=value_grad, num_warps=warps,
            enable_fp_fusion=FP_FUSION,
        )
    return (
        None if grad_value is None else grad_value.to(value.dtype),
        grad_loc.to(locations.dtype),
        grad_wt.to(weights.dtype),
    )
