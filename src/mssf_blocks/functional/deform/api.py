"""The public functions of multi-scale deformable sampling: :func:`ms_deform_sample` (no projection, any
``Mv``) and :func:`ms_deform_sample_project` (with MSDFF's per-head value projection). Each checks its
inputs once and hands them to one path: the float64 reference (``reference.py``), the embedding-bag
path (``bag.py``), or the sampling op (``op.py``: the device's backend).
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple, Union

import torch  # noqa: F401 (the docstring examples use it)
from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.deform.bag import sample, sample_project_chunked
from mssf_blocks.checks.deform import _check_deform_inputs, check_projection
from mssf_blocks.functional.deform.op import sample_project_unchecked
from mssf_blocks.functional.deform.reference import ms_deform_sample_reference

__all__ = ["ms_deform_sample", "ms_deform_sample_project"]

_METHODS = ("auto", "reference", "fast")
_PROJECT_METHODS = ("chunked", "touched", "auto")


def ms_deform_sample(
    values: Sequence[Tensor],
    image_index: Tensor,
    locations: Tensor,
    weights: Tensor,
    method: str = "auto",
    return_mass: bool = False,
) -> Union[Tensor, Tuple[Tensor, Tensor]]:
    """Multi-scale deformable sampling (the core of Deformable DETR's attention) for sparse queries.

    ``out[q, m] = sum_{l, p} weights[q, m, l, p] * bilinear(values[l][image_index[q], m'], locations[q, m, l, p])``
    with ``m' = m`` if ``Mv == M`` and ``m' = 0`` if ``Mv == 1`` (one value map shared by all heads,
    e.g. raw image channels when the value projection is applied after sampling). Bilinear sampling
    uses ``align_corners=False`` and zero padding (pixel ``x = u * W_l - 0.5``).

    Args:
        values: ``L`` levels, each ``(I, Mv, D, H_l, W_l)``; ``I`` images (e.g. ``B * V``), the same
            ``I``, ``Mv``, ``D``, dtype and device on every level (levels with different channels
            must be projected to a common ``D`` first). The fast path reads each level as a
            ``(I * Mv * H_l * W_l, D)`` table: pass channels-last memory (stride 1 along ``D``, e.g.
            ``x.contiguous(memory_format=torch.channels_last)`` before the reshape to 5-d) to make that
            a free view; otherwise each call copies every level once.
        image_index: ``(Q,)`` integer image of every query, in ``[0, I)``.
        locations: ``(Q, M, L, P, 2)`` normalised ``(u, v)`` sampling locations (finite; outside
            ``[0, 1]`` reads zeros).
        weights: ``(Q, M, L, P)`` attention weights (any finite values; softmax is the caller's).
        method: ``"fast"`` (embedding-bag over the 4 bilinear corners; O(Q) time and memory),
            ``"reference"`` (per-level ``F.grid_sample``) or ``"auto"`` (= ``"fast"``). Not the sampling
            op: the op samples values projected per head from maps shared by the heads, while these
            values may be per head (``Mv = M``) and are not projected (an identity projection through
            the op would add ``Q * M * D * D`` multiply-adds), and ``mass`` is no output of the op.
        return_mass: also return ``mass[q, m] = sum_{l, p} weights * (sum of the in-image bilinear
            corner weights)``, the factor of a value-projection bias applied after sampling.

    Returns:
        ``(Q, M, D)`` sampled values, and ``(Q, M)`` mass if ``return_mass``. Differentiable w.r.t.
        ``values``, ``locations`` and ``weights``. The fast path returns a transposed view of
        head-major ``(M, Q, D)`` memory (use ``reshape``, not ``view``, to flatten it); a per-head
        ``einsum``/``bmm`` reads it without a copy.

    Raises:
        MSSFError: naming the argument on mismatched levels (``I``, ``Mv``, ``D``, dtype), shapes,
            ``Mv`` not in ``{1, M}``, ``L`` mismatch, out-of-range ``image_index``, non-finite
            ``locations``/``weights`` or an unknown ``method``.

    Example:
        >>> val = [torch.arange(4.0).view(1, 1, 1, 2, 2)]  # one 2x2 level, I = Mv = D = 1
        >>> loc = torch.tensor([0.75, 0.25]).view(1, 1, 1, 1, 2)  # centre of pixel (y=0, x=1)
        >>> ms_deform_sample(val, torch.tensor([0]), loc, torch.ones(1, 1, 1, 1)).item()
        1.0
    """
    if method not in _METHODS:
        raise MSSFError(f"method: expected one of {_METHODS}, got {method!r}")
    if not isinstance(return_mass, bool):
        raise MSSFError(f"return_mass: expected a bool, got {type(return_mass).__name__}")
    levels, _ = _check_deform_inputs(values, image_index, locations, weights)
    if method == "reference":
        return ms_deform_sample_reference(levels, image_index, locations, weights, return_mass=return_mass)
    return sample(levels, image_index, locations, weights, return_mass)


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
    * ``"touched"`` (``Mv = 1`` only; the sampling op with its CPU backend forced): per level, mark the pixels that some in-map bilinear corner
      reads (``U <= min(I * H_l * W_l, Q * M * P * 4)``) and run the cheapest of four exact plans by a
      cost model measured on a CPU (``docs/fusion.md``): project every pixel, project only the ``U``
      touched pixels (one GEMM for all heads), then sample ``d`` channels per head and point; or
      sample the touched pixels' ``D`` raw channels (from a gathered table, or in place for
      channels-last levels), then project per head. When gradients are needed the costs include the
      backward and the projected plans sample with ``F.grid_sample`` (cheaper backward). Memory
      ``O(U * M * d + Q * M * P * 4)`` per level (plus the dense projected map with gradients);
      ``chunk_size`` is ignored.
    * ``"auto"``: the sampling op (:func:`~mssf_blocks.functional.deform_sample_project`, the device's
      backend: ``"touched"`` on the CPU) when ``Mv = 1``, else ``"chunked"``.

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
    check_projection(proj_weight, proj_bias, levels, dims)
    if chunk_size is not None and (isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1):
        raise MSSFError(f"chunk_size: expected a positive int or None, got {chunk_size!r}")
    if method not in _PROJECT_METHODS:
        raise MSSFError(f"method: expected one of {_PROJECT_METHODS}, got {method!r}")
    if method == "touched" and dims["Mv"] != 1:
        raise MSSFError(
            f"values: method='touched' needs Mv = 1 (raw maps shared by all heads), got Mv = {dims['Mv']}"
        )
    if method == "touched" or (method == "auto" and dims["Mv"] == 1):
        # the sampling op: "touched" forces its CPU backend, "auto" takes the device's
        return sample_project_unchecked(levels, image_index, locations, weights, proj_weight, proj_bias,
                                        "touched" if method == "touched" else "auto")
    return sample_project_chunked(levels, image_index, locations, weights, proj_weight, proj_bias, chunk_size)
