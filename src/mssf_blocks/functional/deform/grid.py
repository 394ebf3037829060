"""The grid path of the sampling op: project every pixel, then one ``F.grid_sample`` per level.

Static shapes (no ``nonzero``, no ``.item()``): MSDFF's path under an ONNX export (``Conv`` +
``GridSample``, opset 16+; other graph captures take ``bag.sample_project_static``), the static plan of
``torch.compile`` where ``plan_costs.COMPILED_TRAINING`` asks for it, the path of devices without a
backend of their own, and the op's fallback on CUDA. Every query is sampled in every image of the
batch and keeps its own image's result (a mask, no gather of per-image query lists): cost and memory
grow with the number of images ``I = B * V``, the same as a per-image loop for ``I = 1``, ``I`` times it
otherwise. Inputs unchecked.
"""

from __future__ import annotations

from typing import List, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["grid_sample_static", "project_levels", "sample_project"]


def _select_image(per_image: Tensor, image_index: Tensor) -> Tensor:
    """``per_image (I, Q, ...)`` -> ``(Q, ...)``: row ``q`` of image ``image_index[q]`` (a where-mask sum).

    ``torch.where`` (not a product with a one-hot mask) so that a non-finite sample of another image
    cannot leak in; its backward sends each query's gradient to its own image only.
    """
    num_images = per_image.shape[0]
    if num_images == 1:
        return per_image[0]
    mine = image_index.view(1, -1) == torch.arange(num_images, device=image_index.device).view(-1, 1)  # (I, Q)
    mine = mine.view(mine.shape + (1,) * (per_image.dim() - 2))
    return torch.where(mine, per_image, per_image.new_zeros(())).sum(0)


def grid_sample_static(
    values: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor
) -> Tensor:
    """``F.grid_sample`` formulation of :func:`~mssf_blocks.functional.ms_deform_sample` with static shapes.

    Args:
        values: ``L`` levels ``(I, Mv, D, H_l, W_l)`` with ``Mv`` 1 (shared by all heads) or ``M``.
        image_index: ``(Q,)`` integer image of every query, in ``[0, I)``.
        locations: ``(Q, M, L, P, 2)`` normalised ``(u, v)`` (grid ``2 * loc - 1``, ``align_corners=False``,
            zero padding: the conventions of the other paths).
        weights: ``(Q, M, L, P)``.

    Returns:
        ``(Q, M, D)``. No input validation (the public functions validate, then call this).
    """
    q, m, _, p, _ = locations.shape
    out: Optional[Tensor] = None
    grid = 2.0 * locations - 1.0
    for lvl, val in enumerate(values):
        num_images, mv, d, h, w = val.shape
        g = grid[:, :, lvl]  # (Q, M, P, 2)
        wt = weights[:, :, lvl]  # (Q, M, P)
        if mv == 1:
            # one map for all heads: every head's points are extra grid columns, (I, Q, M * P, 2)
            gi = g.reshape(1, q, m * p, 2).expand(num_images, q, m * p, 2)
            s = F.grid_sample(val[:, 0], gi, mode="bilinear", padding_mode="zeros", align_corners=False)
            s = (s.view(num_images, d, q, m, p) * wt.view(1, 1, q, m, p)).sum(-1)  # (I, D, Q, M)
            s = s.permute(0, 2, 3, 1)  # (I, Q, M, D)
        else:
            # head m samples value head m: the heads are extra images, (I * M, Q, P, 2)
            gi = g.transpose(0, 1).unsqueeze(0).expand(num_images, m, q, p, 2).reshape(num_images * m, q, p, 2)
            s = F.grid_sample(val.reshape(num_images * m, d, h, w), gi, mode="bilinear", padding_mode="zeros",
                              align_corners=False)  # (I * M, d, Q, P)
            s = (s.view(num_images, m, d, q, p) * wt.permute(1, 0, 2).reshape(1, m, 1, q, p)).sum(-1)  # (I, M, d, Q)
            s = s.permute(0, 3, 1, 2)  # (I, Q, M, d)
        part = _select_image(s, image_index)
        out = part if out is None else out + part
    return out


def project_levels(levels: List[Tensor], proj_weight: Tensor, proj_bias: Tensor) -> List[Tensor]:
    """Raw levels ``(I, 1, C, H_l, W_l)`` projected per head, every pixel in one GEMM per level:
    ``(I, M, d, H_l, W_l)`` views of ``(I, H_l, W_l, M * d)`` memory (``proj_weight (M, d, C)``,
    ``proj_bias (M, d)``)."""
    m, d, c = proj_weight.shape
    return [F.linear(lvl[:, 0].permute(0, 2, 3, 1), proj_weight.reshape(m * d, c), proj_bias.reshape(m * d))
            .unflatten(-1, (m, d)).permute(0, 3, 4, 1, 2) for lvl in levels]


def project_levels_conv(levels: List[Tensor], proj_weight: Tensor, proj_bias: Tensor) -> List[Tensor]:
    """:func:`project_levels` as a 1 x 1 convolution of the ``(I, C, H_l, W_l)`` maps: ``(I, M, d, H_l, W_l)``
    contiguous views of the ``(I, M * d, H_l, W_l)`` output. The form for ONNX (one ``Conv`` on the NCHW
    input and a free reshape for ``GridSample``, where the linear form adds a ``Transpose`` of every level
    and a ``MatMul``: 1.6-1.8x slower in onnxruntime, one core, MSDFF at the paper's width on a VoD image,
    N = 2,500 / 8,000; docs/deployment.md)."""
    m, d, c = proj_weight.shape
    return [F.conv2d(lvl[:, 0], proj_weight.reshape(m * d, c, 1, 1), proj_bias.reshape(m * d))
            .unflatten(1, (m, d)) for lvl in levels]


def sample_project(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                   proj_weight: Tensor, proj_bias: Tensor, conv: bool = False) -> Tensor:
    """``(Q, M, d)``: the op's formula by the grid path (:func:`project_levels`, or with ``conv``
    :func:`project_levels_conv`, then :func:`grid_sample_static`)."""
    project = project_levels_conv if conv else project_levels
    return grid_sample_static(project(levels, proj_weight, proj_bias), image_index, locations, weights)
