"""The grid path of the sampling op: project every pixel, then one ``F.grid_sample`` per level.

Static shapes (no ``nonzero``, no ``.item()``): MSDFF's path under an ONNX export (``Conv`` +
``GridSample``, opset 16+, or per level the raw level's ``GridSample`` projected after:
:func:`sample_project_onnx`; other graph captures take ``bag.sample_project_static``), the static plan of
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

from mssf_blocks.functional.deform.bag import plan_queries
from mssf_blocks.functional.plan_costs import _ONNX_GRID_RAW_COST, onnx_sampling_per_level

__all__ = ["grid_sample_static", "project_levels", "sample_project", "sample_project_onnx"]


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
    return [F.conv2d(lvl.flatten(0, 1), proj_weight.reshape(m * d, c, 1, 1), proj_bias.reshape(m * d))
            .unflatten(1, (m, d)) for lvl in levels]  # (flatten: a Reshape in ONNX, [:, 0] a Gather copying the level)


def sample_project(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                   proj_weight: Tensor, proj_bias: Tensor) -> Tensor:
    """``(Q, M, d)``: the op's formula by the grid path (:func:`project_levels`, then :func:`grid_sample_static`)."""
    return grid_sample_static(project_levels(levels, proj_weight, proj_bias), image_index, locations, weights)


def _raw_pays(level: Tensor, q, m: int, p: int, d: int) -> bool:
    """Whether, in onnxruntime, sampling the ``C`` raw channels of ``level (I, 1, C, H, W)`` at every point of
    every head costs less than projecting every pixel (``C x M * d``) and sampling ``d`` channels per head
    (``plan_costs._ONNX_GRID_RAW_COST``; planned for ``STATIC_PLAN_QUERIES`` queries when ``q`` is symbolic)."""
    num_images, _, c, h, w = level.shape
    points = num_images * plan_queries(q) * m * p  # (every query in every image)
    return points * c * _ONNX_GRID_RAW_COST < num_images * h * w * c * m * d


def _sample_first(level: Tensor, image_index: Tensor, locations: Tensor, weights: Tensor, proj_weight: Tensor,
                  proj_bias: Tensor) -> Tensor:
    """``(Q, M, d)`` of one level ``(I, 1, C, H, W)`` (``locations (Q, M, 1, P, 2)``, ``weights (Q, M, 1, P)``):
    one ``GridSample`` of the raw channels at every point of every head (head-major columns), head ``m``'s
    rows of the projection applied to its points (a batched ``MatMul``: ``M * d`` of the ``C x C`` per point,
    cheaper in onnxruntime than weighting the ``C``-channel samples), then the attention-weighted sum over
    the points, and the bias times the in-image bilinear weight mass (a ``GridSample`` of a ones map)."""
    num_images, _, c, h, w = level.shape
    q, m, _, p, _ = locations.shape
    d = proj_weight.shape[1]
    maps = level.flatten(0, 1)  # (I, C, H, W): a Reshape in ONNX (``[:, 0]`` would be a Gather copying the level)
    grid = (2.0 * locations[:, :, 0] - 1.0).transpose(0, 1).reshape(1, m, q * p, 2).expand(num_images, m, q * p, 2)
    wt = weights[:, :, 0].transpose(0, 1).reshape(1, m, q, p)
    sampled = F.grid_sample(maps, grid, mode="bilinear", padding_mode="zeros", align_corners=False)  # (I, C, M, QP)
    heads = torch.matmul(proj_weight, sampled.transpose(1, 2))  # (I, M, d, Q * P)
    heads = (heads.view(num_images, m, d, q, p) * wt.unsqueeze(2)).sum(-1)  # (I, M, d, Q)
    ones = maps.new_ones(num_images, 1, h, w)
    inside = F.grid_sample(ones, grid, mode="bilinear", padding_mode="zeros", align_corners=False)  # (I, 1, M, QP)
    mass = (inside.view(num_images, m, q, p) * wt).sum(-1)  # (I, M, Q)
    heads = heads + mass.unsqueeze(2) * proj_bias.view(1, m, d, 1)
    return _select_image(heads.permute(0, 3, 1, 2), image_index)


def sample_project_onnx(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                        proj_weight: Tensor, proj_bias: Tensor) -> Tensor:
    """``(Q, M, d)``: the op's formula as MSDFF's ONNX graph takes it (``GridSample``, ``Conv``, ``MatMul`` and
    elementwise operators, which TensorRT parses; no embedding bag, which ONNX writes as a ``Loop``).

    Per level (where ``plan_costs.ONNX_SAMPLING`` of the levels' device says so; else every level
    project-first) the cheaper in onnxruntime
    (:func:`_raw_pays`) of project-first (a 1 x 1 ``Conv`` over every pixel, ``GridSample`` of ``d`` channels
    per head) and sample-first (:func:`_sample_first`: the raw level sampled at every point, projected per
    head after). Sampling is linear, so both are exact; the bias enters sample-first times the in-image
    weight mass, as a projected pixel outside the map reads zero, bias included.
    """
    q, m, _, p, _ = locations.shape
    d = proj_weight.shape[1]
    per_level = onnx_sampling_per_level(levels[0].device.type)
    out: Optional[Tensor] = None
    for i, level in enumerate(levels):
        loc, wt = locations[:, :, i : i + 1], weights[:, :, i : i + 1]
        if per_level and _raw_pays(level, q, m, p, d):
            part = _sample_first(level, image_index, loc, wt, proj_weight, proj_bias)
        else:
            part = grid_sample_static(project_levels_conv([level], proj_weight, proj_bias), image_index, loc, wt)
        out = part if out is None else out + part
    return out
