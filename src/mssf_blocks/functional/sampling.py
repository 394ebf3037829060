"""Bilinear sampling of image features at one point per voxel and camera (SFF, query initialisation),
and the mean over the cameras in which a voxel is valid.

Conventions (see ``docs/conventions.md``): locations are normalised ``[0, 1]`` image coordinates
relative to the full image, sampled bilinearly with ``align_corners=False`` and zero padding, i.e.
the pixel coordinate on a level of width ``W_l`` is ``x = u * W_l - 0.5`` (pixel ``i``'s centre at
``u = (i + 0.5) / W_l``). Corners outside the map read zeros, they are never clamped to the edge.

:func:`bilinear_sample` costs O(points), not O(pixels): on the CPU it gathers the distinct corner
pixels of its points once and bags them (the CPU plans of the sampling op,
``functional/deform/touched``), under ``torch.compile`` too (as one opaque op,
``functional/deform/gather_op.py``); while an exporter captures a graph and off the CPU it runs the op's
grid path (``functional/deform/grid.py``). Multi-scale deformable sampling (MSDFF) is ``functional/deform``
(``ms_deform_sample`` is re-exported here, its earlier home).
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import (
    INDEX_DTYPES,
    check_dtype,
    check_finite,
    check_floating,
    check_index_range,
    check_shape,
    check_tensor,
)
from mssf_blocks.static_path import use_static_path
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.deform import ms_deform_sample, ms_deform_sample_reference  # noqa: F401 (their earlier home)
from mssf_blocks.functional.deform import touched
from mssf_blocks.functional.deform.gather_op import bilinear_gather, compiled_gather
from mssf_blocks.functional.deform.grid import grid_sample_static
from mssf_blocks.functional.plan_costs import bilinear_auto_method

__all__ = ["bilinear_sample", "camera_mean"]



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
            ``B`` images and keeps its own) or ``"auto"``: ``"gather"`` on the CPU (2-6x faster there;
            under ``torch.compile`` as one opaque op, ``functional/deform/gather_op.py``), ``"grid"`` on
            other devices and while an exporter captures a graph (export, ONNX, tracing;
            ``functional/plan_costs.py``). Equal results.

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
    check_dtype(batch_index, "batch_index", INDEX_DTYPES)
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
        if compiled_gather(image.device.type):  # torch.compile on the CPU: the gather as one opaque op
            rows = [bilinear_gather(image[:, cam : cam + 1], batch_index, uv[:, cam]) for cam in range(v)]
            return rows[0].unsqueeze(1) if v == 1 else torch.stack(rows, 1)  # (N, V, C) (gather_op.py)
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
    rows = [touched.sample_points(image[:, cam : cam + 1], batch_index, uv[:, cam]) for cam in range(v)]
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
