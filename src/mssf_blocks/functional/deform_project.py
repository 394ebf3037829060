"""Deformable sampling followed by MSDFF's per-head value projection (:func:`ms_deform_sample_project`)."""

from __future__ import annotations

from typing import Optional, Sequence

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .._checks import check_dtype, check_shape
from ..errors import MSSFError
from .sampling import _check_deform_inputs, _ms_deform_sample_fast
from .touched import _ms_deform_sample_touched

__all__ = ["ms_deform_sample_project"]


def _sample_project_level(
    locations: Tensor,
    weights: Tensor,
    image_index: Tensor,
    proj_weight: Tensor,
    proj_bias: Optional[Tensor],
    value: Tensor,
) -> Tensor:
    """One level of :func:`ms_deform_sample_project` for ``locations (Q, M, 1, P, 2)``."""
    sampled, mass = _ms_deform_sample_fast([value], image_index, locations, weights, True)
    # sampled is a (Q, M, D) view of head-major (M, Q, D) memory: the per-head bmm reads it in place.
    out = torch.bmm(sampled.transpose(0, 1), proj_weight.transpose(1, 2)).transpose(0, 1)  # (Q, M, d)
    if proj_bias is not None:
        out = out + mass[..., None] * proj_bias
    return out


_PROJECT_METHODS = ("chunked", "touched", "auto")


def ms_deform_sample_project(
    values: Sequence[Tensor],
    image_index: Tensor,
    locations: Tensor,
    weights: Tensor,
    proj_weight: Tensor,
    proj_bias: Optional[Tensor] = None,
    chunk_size: Optional[int] = 512,
    method: str = "chunked",
) -> Tensor:
    """:func:`ms_deform_sample` followed by a per-head linear projection (MSDFF's value projection).

    ``out[q, m] = proj_weight[m] @ sampled[q, m] + mass[q, m] * proj_bias[m]`` where
    ``sampled, mass = ms_deform_sample(..., return_mass=True)``; equivalently (sampling is linear and
    the bias only enters where bilinear corners fall inside the image) the bilinear sample of the
    projected map ``proj_weight[m] @ values + proj_bias[m]`` with zero padding. Two methods:

    * ``"chunked"`` (default): sample the raw ``D`` channels once per head and point, then project.
      Queries are processed ``chunk_size`` at a time and, when gradients are needed, each
      (chunk, level) block is recomputed in backward (activation checkpointing), so memory is
      ``O(chunk_size * M * (D + L * P))`` instead of ``O(Q * M * L * P * D)`` at the price of one
      more sampling pass in backward. Cost ``O(Q * M * L * P * 4 * D)`` scattered row reads.
    * ``"touched"`` (``Mv = 1`` only): per level, mark the pixels that some in-map bilinear corner
      reads (``U <= min(I * H_l * W_l, Q * M * P * 4)``) and run the cheapest of four exact plans by a
      cost model measured on a CPU (``docs/fusion.md``): project every pixel, project only the ``U``
      touched pixels (one GEMM for all heads), then sample ``d`` channels per head and point; or
      sample the touched pixels' ``D`` raw channels (from a gathered table, or in place for
      channels-last levels), then project per head. When gradients are needed the costs include the
      backward and the projected plans sample with ``F.grid_sample`` (cheaper backward). Memory
      ``O(U * M * d + Q * M * P * 4)`` per level (plus the dense projected map with gradients);
      ``chunk_size`` is ignored.
    * ``"auto"``: ``"touched"`` when ``Mv = 1``, else ``"chunked"``.

    Args:
        values, image_index, locations, weights: as :func:`ms_deform_sample` (``Mv`` 1 or ``M``).
        proj_weight: ``(M, d, D)`` per-head projection (e.g. ``value_proj.weight.view(M, d, D)``).
        proj_bias: ``(M, d)`` per-head bias or ``None``.
        chunk_size: queries per chunk of ``"chunked"``; ``None`` processes all queries at once (no
            recomputation).
        method: ``"chunked"``, ``"touched"`` or ``"auto"``.

    Returns:
        ``(Q, M, d)``.

    Example:
        >>> val = [torch.ones(1, 1, 2, 2, 2)]  # I = Mv = 1, D = 2, a 2x2 map of ones
        >>> loc = torch.tensor([0.0, 0.0]).view(1, 1, 1, 1, 2)  # image corner: 1/4 of the mass inside
        >>> w, b = torch.ones(1, 1, 2), torch.full((1, 1), 10.0)
        >>> ms_deform_sample_project(val, torch.tensor([0]), loc, torch.ones(1, 1, 1, 1), w, b).item()
        3.0
    """
    levels, dims = _check_deform_inputs(values, image_index, locations, weights)
    check_shape(proj_weight, "proj_weight", ("M", None, "D"), dims)
    check_dtype(proj_weight, "proj_weight", (levels[0].dtype,), hint=" (must match values)")
    if proj_bias is not None:
        check_shape(proj_bias, "proj_bias", ("M", proj_weight.shape[1]), dims)
        check_dtype(proj_bias, "proj_bias", (levels[0].dtype,), hint=" (must match values)")
    if chunk_size is not None and (isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1):
        raise MSSFError(f"chunk_size: expected a positive int or None, got {chunk_size!r}")
    if method not in _PROJECT_METHODS:
        raise MSSFError(f"method: expected one of {_PROJECT_METHODS}, got {method!r}")
    if method == "touched" and dims["Mv"] != 1:
        raise MSSFError(
            f"values: method='touched' needs Mv = 1 (raw maps shared by all heads), got Mv = {dims['Mv']}"
        )
    if method == "touched" or (method == "auto" and dims["Mv"] == 1):
        return _ms_deform_sample_touched(levels, image_index, locations, weights, proj_weight, proj_bias)
    q = dims["Q"]
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
