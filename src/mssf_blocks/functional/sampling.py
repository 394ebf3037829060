"""Bilinear and multi-scale deformable sampling of image features at sparse query locations.

Conventions (see ``docs/conventions.md``): locations are normalised ``[0, 1]`` image coordinates
relative to the full image, sampled bilinearly with ``align_corners=False`` and zero padding, i.e.
the pixel coordinate on a level of width ``W_l`` is ``x = u * W_l - 0.5`` (pixel ``i``'s centre at
``u = (i + 0.5) / W_l``). Corners outside the map read zeros, they are never clamped to the edge.

Two functions sit under the fusion modules:

* :func:`bilinear_sample` (SFF, query initialisation): one point per voxel and camera.
* :func:`ms_deform_sample` (MSDFF): the sampling core of Deformable DETR's multi-scale deformable
  attention (Zhu et al., "Deformable DETR", ICLR 2021, eq. 3),
  ``out[q, m] = sum_{l, p} weights[q, m, l, p] * bilinear(values[l][image_index[q], m], locations[q, m, l, p])``.

Radar queries are sparse (10^3-10^4 voxels against ~10^5 pixels), so both cost O(queries), not
O(pixels): :func:`ms_deform_sample`'s fast path turns the four bilinear corners of every point into
rows of a (pixels x D) table and reduces them with ``embedding_bag(mode="sum")`` weighted by
``bilinear weight * attention weight`` (never materialising a gathered ``(corners, D)`` tensor);
autograd carries the per-corner weight gradient back to ``locations`` and ``weights``. The
``"reference"`` path is the usual per-level ``F.grid_sample`` formulation and is kept for tests.
:func:`ms_deform_sample_project` adds MSDFF's value projection; its ``"touched"`` method projects
only the pixels that some bilinear corner reads (found with a bool mark array over the level), and
:func:`bilinear_sample` gathers the distinct corner pixels of its points once (``method="gather"``).
"""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple, Union

import torch
import torch.nn.functional as F
from torch import Tensor

from .. import _compat
from .._checks import check_dtype, check_finite, check_floating, check_index_range, check_shape, check_tensor
from .._static import use_static_path
from ..errors import MSSFError
from .plan_costs import bilinear_auto_method
from .static import grid_sample_static
from .raw_blocks import _level, _pixel_coordinate, _sorted_points
from .touched import _is_row_table, _touched_level

__all__ = [
    "bilinear_sample",
    "camera_mean",
    "ms_deform_sample",
    "ms_deform_sample_reference",
]

_INT_DTYPES = (torch.int32, torch.int64)
_METHODS = ("auto", "reference", "fast")


# ---------------------------------------------------------------------------------------------------
# bilinear_sample / camera_mean
# ---------------------------------------------------------------------------------------------------
def bilinear_sample(
    image: Tensor, uv: Tensor, batch_index: Tensor, valid: Optional[Tensor] = None, method: str = "auto"
) -> Tensor:
    """Bilinear sample of one image level at one normalised point per voxel and camera.

    ``align_corners=False`` and zero padding: the pixel coordinate is ``x = u * W - 0.5``, so a point
    at ``u = (i + 0.5) / W`` returns pixel ``i`` exactly and points outside the image read zeros.

    The cost scales with ``N * V`` (per camera, the distinct pixels read by the 4 bilinear corners of
    the points are gathered once and summed with ``embedding_bag``), not with ``H * W`` (except an
    ``O(B * H * W)`` bool mark array and, in backward, the dense image gradient autograd allocates).

    Args:
        image: ``(B, C, H, W)`` (one camera) or ``(B, V, C, H, W)`` floating feature map.
        uv: ``(N, V, 2)`` normalised ``(u, v)`` of every voxel in every camera.
        batch_index: ``(N,)`` integer batch of every voxel, in ``[0, B)``.
        valid: ``(N, V)`` bool, ``False`` where the voxel is behind/not seen by the camera
            (``None``: all valid). Invalid entries return exact zeros, pass no gradient to ``image``
            or ``uv``, and may hold any ``uv`` (even NaN).
        method: ``"gather"`` (distinct corner pixels gathered once, ``embedding_bag``; data-dependent
            sizes), ``"grid"`` (``F.grid_sample``, static shapes: every point is sampled in each of the
            ``B`` images and keeps its own) or ``"auto"``: ``"gather"`` on the CPU (2-6x faster there),
            ``"grid"`` on other devices and while a graph is captured (``torch.compile``, export,
            tracing; ``functional/plan_costs.py``). Equal results.

    Returns:
        ``(N, V, C)`` sampled features.

    Raises:
        MSSFError: on wrong shapes/dtypes, out-of-range ``batch_index`` or non-finite valid ``uv``.

    Example:
        >>> img = torch.arange(6.0, dtype=torch.float64).view(1, 1, 2, 3)  # (B, C, H, W)
        >>> # centres of pixels (y, x) = (0, 0) and (1, 2)
        >>> uv = torch.tensor([[[0.5 / 3, 0.5 / 2]], [[2.5 / 3, 1.5 / 2]]], dtype=torch.float64)
        >>> bilinear_sample(img, uv, torch.tensor([0, 0])).flatten().tolist()
        [0.0, 5.0]
    """
    if method not in ("auto", "gather", "grid"):
        raise MSSFError(f"method: expected one of ('auto', 'gather', 'grid'), got {method!r}")
    check_tensor(image, "image")
    if image.dim() == 4:
        image = image.unsqueeze(1)
    elif image.dim() != 5:
        raise MSSFError(
            f"image: expected a 4-d (B, C, H, W) or 5-d (B, V, C, H, W) tensor, got shape {tuple(image.shape)}"
        )
    check_floating(image, "image")
    b, v, c, h, w = image.shape
    dims = {"V": v}
    check_shape(uv, "uv", ("N", "V", 2), dims)
    check_dtype(uv, "uv", (image.dtype,), hint=" (must match image)")
    n = dims["N"]
    check_shape(batch_index, "batch_index", (n,))
    check_dtype(batch_index, "batch_index", _INT_DTYPES)
    check_index_range(batch_index, "batch_index", b, "B")
    if valid is not None:
        check_shape(valid, "valid", (n, v))
        check_dtype(valid, "valid", (torch.bool,))
        # Invalid entries may carry anything (e.g. uv = -1 or NaN behind the camera): replace them by
        # a finite point; torch.where passes no gradient to the replaced uv.
        uv = torch.where(valid[..., None], uv, uv.new_full((), -1.0))
    check_finite(uv, "uv" if valid is None else "uv (valid entries)")

    if method == "auto":
        method = bilinear_auto_method(image.device.type, use_static_path())
    if method == "grid":
        # Static shapes (compile / export): one grid_sample per camera over all points, no n == 0 branch.
        ones = uv.new_ones(n, 1, 1, 1)
        out = torch.stack([grid_sample_static([image[:, cam : cam + 1]], batch_index, uv[:, cam].view(n, 1, 1, 1, 2),
                                               ones)[:, 0] for cam in range(v)], 1)  # (N, V, C)
        return out if valid is None else torch.where(valid[..., None], out, out.new_zeros(()))
    out = image.new_zeros(n, v, c)
    if n == 0 or c == 0:
        return out + 0 * uv.sum() if uv.requires_grad else out
    # Every camera: the 4 bilinear corners of every point, the distinct in-map corner pixels gathered
    # once (sorted reads along each channel plane), one embedding_bag over that compact table (the
    # "sample" plan of the touched method). For NCHW maps this reads each needed pixel once instead of
    # 4 scattered channel planes per point (grid_sample): measured 2-6x faster on one core for 10^3-10^4
    # points on 256-channel NCHW P2/P3 levels, clustered or spread. A channels-last map is its own row
    # table: its rows are bagged in place, no gather (the "direct" plan).
    ones = uv.new_ones(n, 1, 1, 1)
    rows = []
    for cam in range(v):
        lv = _level(*_sorted_points(uv[:, cam].view(n, 1, 1, 1, 2), ones, [(h, w)]), 0)
        plan = "direct" if _is_row_table(image[:, cam : cam + 1]) else "sample"
        rows.append(_touched_level(image[:, cam : cam + 1], batch_index, lv, None, None, 1, plan))
    # Invalid entries are exact zeros without a mask: their point (-1, -1) has all four corners outside
    # the map, which read nothing (weight 0 on a finite row, or no row at all when the table's last row
    # is not finite: _bag_raw), so no gradient either. (A torch.where over every row cost 0.8 ms at
    # 2,500 x 256.)
    return rows[0].unsqueeze(1) if v == 1 else torch.stack(rows, 1)  # (N, V, C)


def camera_mean(x: Tensor, valid: Tensor) -> Tensor:
    """Mean over the cameras in which each voxel is valid.

    Args:
        x: ``(N, V, C)`` per-camera features.
        valid: ``(N, V)`` bool.

    Returns:
        ``(N, C)``: the mean of ``x[n, v]`` over ``v`` with ``valid[n, v]``; zeros (and no gradient)
        for voxels valid in no camera. Invalid entries never reach the result, even if NaN.

    Example:
        >>> x = torch.tensor([[[1.0], [3.0]], [[5.0], [7.0]]])
        >>> camera_mean(x, torch.tensor([[True, True], [False, False]])).flatten().tolist()
        [2.0, 0.0]
    """
    dims: dict = {}
    check_shape(x, "x", ("N", "V", "C"), dims)
    check_floating(x, "x")
    check_shape(valid, "valid", ("N", "V"), dims)
    check_dtype(valid, "valid", (torch.bool,))
    if x.shape[1] == 1:  # one camera: the mean is the valid entry itself (same numbers, one pass)
        return torch.where(valid, x[:, 0], x.new_zeros(()))
    total = torch.where(valid[..., None], x, x.new_zeros(())).sum(dim=1)
    count = valid.sum(dim=1, keepdim=True).clamp(min=1).to(x.dtype)
    return total / count


# ---------------------------------------------------------------------------------------------------
# ms_deform_sample
# ---------------------------------------------------------------------------------------------------
def _check_deform_inputs(
    values: Sequence[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor
) -> Tuple[List[Tensor], dict]:
    if isinstance(values, Tensor) or not isinstance(values, (list, tuple)):
        raise MSSFError(
            f"values: expected a list/tuple of L tensors (I, Mv, D, H_l, W_l), got {type(values).__name__}"
        )
    if len(values) == 0:
        raise MSSFError("values: expected at least one level, got an empty sequence")
    dims: dict = {}
    levels = list(values)
    for lvl, val in enumerate(levels):
        name = f"values[{lvl}]"
        check_shape(val, name, ("I", "Mv", "D", None, None), dims)
        check_floating(val, name)
        if lvl and (val.dtype != levels[0].dtype or val.device != levels[0].device):
            raise MSSFError(
                f"{name}: expected dtype {levels[0].dtype} on {levels[0].device} like values[0], "
                f"got {val.dtype} on {val.device}"
            )
        if val.shape[-1] == 0 or val.shape[-2] == 0:
            raise MSSFError(f"{name}: expected a non-empty map (H_l, W_l >= 1), got shape {tuple(val.shape)}")
    dims["L"] = len(levels)
    check_shape(locations, "locations", ("Q", "M", "L", "P", 2), dims)
    check_dtype(locations, "locations", (levels[0].dtype,), hint=" (must match values)")
    check_shape(weights, "weights", ("Q", "M", "L", "P"), dims)
    check_dtype(weights, "weights", (levels[0].dtype,), hint=" (must match values)")
    if dims["Mv"] not in (1, dims["M"]):
        raise MSSFError(
            f"values: expected Mv = 1 (shared by all heads) or Mv = M = {dims['M']} heads, got Mv = {dims['Mv']}"
        )
    check_shape(image_index, "image_index", (dims["Q"],))
    check_dtype(image_index, "image_index", _INT_DTYPES)
    check_index_range(image_index, "image_index", dims["I"], "I")
    check_finite(locations, "locations")
    check_finite(weights, "weights")
    return levels, dims


def ms_deform_sample_reference(
    values: Sequence[Tensor],
    image_index: Tensor,
    locations: Tensor,
    weights: Tensor,
    return_mass: bool = False,
) -> Union[Tensor, Tuple[Tensor, Tensor]]:
    """Per-level ``F.grid_sample`` formulation of :func:`ms_deform_sample` (no input validation).

    The well-known pure-PyTorch Deformable DETR formulation (grid ``2 * loc - 1``,
    ``align_corners=False``, zero padding), looping over levels and images (never over queries).
    ``mass`` is computed independently by sampling a map of ones.
    """
    q, m, _, p, _ = locations.shape
    num_images, mv, d = values[0].shape[:3]
    out = locations.new_zeros(q, m, d)
    mass = locations.new_zeros(q, m)
    if q == 0:  # keep a graph (of zeros) so that an empty batch can still be backpropagated
        out = out + 0.0 * locations.sum() + 0.0 * weights.sum()
        mass = mass + 0.0 * weights.sum()
    grid = 2.0 * locations - 1.0
    per_image = [(image_index == i).nonzero(as_tuple=True)[0] for i in range(num_images)]
    for lvl, val in enumerate(values):
        h, w = val.shape[-2:]
        for i, sel in enumerate(per_image):
            qi = sel.numel()
            if qi == 0:
                continue
            g = grid[sel, :, lvl]  # (qi, M, P, 2)
            wt = weights[sel, :, lvl]  # (qi, M, P)
            if mv == 1:
                g = g.reshape(1, qi * m, p, 2)
            else:
                g = g.transpose(0, 1)  # (M, qi, P, 2): head m samples value head m
            s = F.grid_sample(val[i], g, mode="bilinear", padding_mode="zeros", align_corners=False)
            s = s.reshape(mv, d, qi, m // mv, p) if mv == 1 else s.reshape(m, d, qi, 1, p)
            # s[.., d, q, m or 1, p] -> (qi, M, D)
            s = s.permute(2, 0, 3, 1, 4).reshape(qi, m, d, p)
            out = out.index_add(0, sel, (s * wt[:, :, None, :]).sum(-1))
            if return_mass:
                ones = val.new_ones(1, 1, h, w)
                gm = g.reshape(1, -1, p, 2)
                one = F.grid_sample(ones, gm, mode="bilinear", padding_mode="zeros", align_corners=False)
                one = one.reshape(mv, -1, p)  # (Mv, qi*M/Mv or qi, P)
                one = one.reshape(qi, m, p) if mv == 1 else one.transpose(0, 1)
                mass = mass.index_add(0, sel, (one * wt).sum(-1))
    return (out, mass) if return_mass else out


def _index_dtype(values: Sequence[Tensor], mv: int) -> torch.dtype:
    # int32 rows halve the index memory and are read natively by embedding_bag.
    rows = max(v.shape[0] * mv * v.shape[-2] * v.shape[-1] for v in values)
    return torch.int32 if rows + 2 * max(v.shape[-1] for v in values) < 2**31 else torch.int64


def _ms_deform_sample_fast(
    values: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor, return_mass: bool
) -> Union[Tensor, Tuple[Tensor, Tensor]]:
    q, m, num_levels, p, _ = locations.shape
    mv, d = values[0].shape[1:3]
    dev = locations.device
    # Work level-major and head-major, (L, M, Q, P): every level's corners are a contiguous slice and
    # the embedding-bag output comes out as (M, Q, D), the layout a per-head projection (bmm) wants.
    locs = locations.permute(2, 1, 0, 3, 4)
    wts = weights.permute(2, 1, 0, 3)
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
    mass = ((ay0 + ay1) * (ax0 + ax1)).sum((0, 3)).t() if return_mass else None  # (Q, M)

    # Row of the top-left corner in level l's table (I * Mv * H_l * W_l, D):
    #   ((image * Mv + head) * H_l + y0) * W_l + x0, computed on points (4x fewer than corners) after
    # clamping x0, y0 to [-1, size] so that huge coordinates cannot overflow; the corners add
    # (0, 1, W_l, W_l + 1). A corner outside the map has weight 0 and any row inside the table will
    # do, hence the final clamp to the table.
    idt = _index_dtype(values, mv)
    heads = torch.arange(m, device=dev, dtype=idt)[:, None] if mv > 1 else torch.zeros((m, 1), dtype=idt, device=dev)
    plane = (image_index.to(idt)[None, :] * mv + heads).view(1, m, q, 1)
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
        part = _compat.embedding_bag(
            rows[lvl].view(m * q, p * 4), table, per_sample_weights=psw[lvl].view(m * q, p * 4), mode="sum"
        )  # (M * Q, D)
        if out is None:
            out = part
        else:
            out += part  # in place: embedding_bag's backward does not need its output
    out = out.view(m, q, d).transpose(0, 1)  # (Q, M, D) view of head-major memory
    return (out, mass) if return_mass else out


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
            ``"reference"`` (per-level ``F.grid_sample``) or ``"auto"`` (= ``"fast"``).
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
    return _ms_deform_sample_fast(levels, image_index, locations, weights, return_mass)
