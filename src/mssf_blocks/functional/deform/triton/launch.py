"""The ``"triton"`` backend of the sampling op: project every pixel, then the Triton kernels.

MSDFF's sampling with value projection, ``out[q, m] = sum_{l,p} w * bilinear(W_m @ raw_l + b_m, loc)``:
the raw levels are flattened into one ``(I, C, S)`` buffer (``S = sum_l H_l * W_l``), projected by one
GEMM into the kernels' ``(I, S, M, d)`` value buffer, and sampled by
:mod:`~mssf_blocks.functional.deform.triton.kernels` (imported here, lazily: this module is imported only when
the backend runs). The backward recomputes the projection (one GEMM, cheaper on a GPU than keeping the
projected map between forward and backward), runs the backward kernel and chains the value gradient
through the projection. No input validation: the op checks at its entry.
"""

from __future__ import annotations

import functools
from typing import List, Optional, Tuple

import torch
from torch import Tensor

from mssf_blocks.functional.deform.triton import kernels as tk


@functools.lru_cache(maxsize=64)
def _level_tensors(sizes: Tuple[Tuple[int, int], ...], device: torch.device) -> Tuple[Tensor, Tensor]:
    """``(L, 2)`` sizes and ``(L,)`` start rows on ``device``, made once per level layout (a host-to-device
    copy per call would synchronise the host with the device)."""
    starts, acc = [], 0
    for h, w in sizes:
        starts.append(acc)
        acc += h * w
    return (torch.tensor(sizes, dtype=torch.int32, device=device),
            torch.tensor(starts, dtype=torch.int32, device=device))


def _level_table(levels: List[Tensor], device: torch.device) -> Tuple[Tensor, Tensor, List[int]]:
    sizes = tuple((int(v.shape[-2]), int(v.shape[-1])) for v in levels)
    shapes, starts = _level_tensors(sizes, device)
    return shapes, starts, [h * w for h, w in sizes]


def _project(levels: List[Tensor], proj_weight: Tensor, proj_bias: Tensor) -> Tuple[Tensor, Tensor]:
    """``raw (I, C, S)`` and the projected ``value (I, S, M, d)`` (contiguous)."""
    m, d, c = proj_weight.shape
    raw = torch.cat([lvl.flatten(-2) for lvl in levels], -1)  # (I, C, S)
    value = torch.addmm(proj_bias.reshape(1, m * d), raw.transpose(1, 2).reshape(-1, c), proj_weight.reshape(m * d, c).t())
    return raw, value.view(raw.shape[0], raw.shape[2], m, d)


def forward(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor, proj_weight: Tensor,
            proj_bias: Tensor, block_q: Optional[int] = None) -> Tensor:
    """``(Q, M, d)``: levels ``(I, C, H_l, W_l)``, projection ``(M, d, C)`` / ``(M, d)``."""
    shapes, starts, _ = _level_table(levels, locations.device)
    _, value = _project(levels, proj_weight, proj_bias)
    return tk.deform_sample_forward(value, shapes, starts, image_index, locations, weights, block_q=block_q)


def backward(grad_out: Tensor, levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
             proj_weight: Tensor, proj_bias: Tensor, value_grad: bool, block_q: Optional[int] = None
             ) -> Tuple[Optional[List[Tensor]], Tensor, Tensor, Optional[Tensor], Optional[Tensor]]:
    """``(grad levels, grad locations, grad weights, grad proj_weight, grad proj_bias)``; the value-side
    gradients are ``None`` unless ``value_grad`` (the value kernel's atomic adds are then compiled out)."""
    shapes, starts, numel = _level_table(levels, locations.device)
    raw, value = _project(levels, proj_weight, proj_bias)
    gv, gl, gw = tk.deform_sample_backward(value, shapes, starts, image_index, locations, weights, grad_out,
                                           value_grad, block_q=block_q)
    if not value_grad:
        return None, gl, gw, None, None
    m, d, c = proj_weight.shape
    gv = gv.view(raw.shape[0], raw.shape[2], m * d)  # (I, S, M * d)
    w_flat = proj_weight.reshape(m * d, c)
    grad_raw = torch.matmul(gv, w_flat).transpose(1, 2)  # (I, C, S)
    grad_levels = [g.reshape(lvl.shape) for g, lvl in zip(grad_raw.split(numel, -1), levels)]
    grad_w = (gv.reshape(-1, m * d).t() @ raw.transpose(1, 2).reshape(-1, c)).view(m, d, c)
    grad_b = gv.sum((0, 1)).view(m, d)
    return grad_levels, gl, gw, grad_w, grad_b
