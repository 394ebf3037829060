"""Output-stage and dtype helpers shared by the image samplers (SFF, MSDFF, QueryInit): the norm layer,
factory arguments, the sampling dtype and ``Linear + norm`` on the voxels a camera sees."""

from __future__ import annotations

from typing import Optional, Type

import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import autocast_off, convert_up
from mssf_blocks.checks.agreement import batch_norm_in_training
from mssf_blocks.checks.geometry import geometry_checks_enabled
from mssf_blocks.static_path import use_static_path
from mssf_blocks.static_path import linear_norm_visible_static
from mssf_blocks.checks.agreement import check_visible_rows


def _norm(norm_layer: Optional[Type[nn.Module]], channels: int, factory: dict) -> nn.Module:
    if norm_layer is None:  # no normalisation (e.g. the MSSF authors' MSDFF): no parameters, no keys
        return nn.Identity()
    # Factory kwargs only when given, so norm layers without device/dtype arguments still work.
    return norm_layer(channels, **factory) if factory else norm_layer(channels)


def _factory(device, dtype) -> dict:
    return {k: v for k, v in (("device", device), ("dtype", dtype)) if v is not None}


def _sampling_dtype(param_or_tensor: Tensor) -> torch.dtype:
    """float64 for float64, else float32: the dtype image sampling runs in (never half precision).

    A normalised coordinate in bfloat16 has a resolution of 2^-8 near 1, about 4 pixels of a
    1,000-pixel-wide level; in float16, 2^-11 (half a pixel).
    """
    return torch.float64 if param_or_tensor.dtype == torch.float64 else torch.float32


def _to_sampling_dtype(x: Tensor, dtype: torch.dtype, name: str, owner: str) -> Tensor:
    """``x`` converted up to the sampling ``dtype`` (float16 / bfloat16 / float32 -> float32 / float64).

    A float64 ``x`` for a float32 sampling is refused rather than rounded: the module is float32.
    """
    return convert_up(x, dtype, name, f"the precision {owner} samples in with its parameters")


_autocast_off = autocast_off  # (the samplers' name for it)


def _linear_bn_visible(linear: nn.Module, norm: nn.Module, x: Tensor, visible: Tensor, static: bool = False) -> Tensor:
    """``norm(linear(x))`` on the visible rows, exact zeros elsewhere (the fusion adds nothing there)."""
    if static or use_static_path():  # (no row gather: a mask, and masked BatchNorm statistics)
        # The count is not on the host here: read where data checks run (CPU, not while capturing a graph), so
        # one seen voxel in training is the same error as on the eager path (a GPU keeps the masked result).
        if batch_norm_in_training(norm) is not None and geometry_checks_enabled(visible):
            check_visible_rows(norm, int(visible.sum()), x.shape[0])
        return linear_norm_visible_static(linear, norm, x, visible)
    rows = visible.nonzero().squeeze(1)
    if rows.numel() == x.shape[0]:  # every voxel seen: no gather / scatter copies
        check_visible_rows(norm, rows.numel(), x.shape[0])
        return norm(linear(x))
    return _linear_bn_rows(linear, norm, x[rows], rows, x.shape[0])


def _linear_bn_rows(linear: nn.Module, norm: nn.Module, x_rows: Tensor, rows: Tensor, n: int) -> Tensor:
    """``(n, C)``: ``norm(linear(x_rows))`` at the rows ``rows`` (the visible voxels), exact zeros elsewhere."""
    check_visible_rows(norm, x_rows.shape[0], n)
    y = norm(linear(x_rows))
    return y.new_zeros(n, y.shape[1]).index_put((rows,), y)


def _corner_aligned_uv(uv: Tensor, height: int, width: int) -> Tensor:
    """``uv`` moved so that ``align_corners=False`` sampling of an ``(height, width)`` level reads what
    ``F.grid_sample(..., align_corners=True)`` reads at ``uv``: pixel ``x = uv * (W_l - 1)``.

    ``align_corners=False`` reads pixel ``uv' * W_l - 0.5``, so ``uv' = (uv * (W_l - 1) + 0.5) / W_l``
    (and the same in ``v``); zero padding is the same in both.
    """
    scale = uv.new_tensor([(width - 1) / width, (height - 1) / height])
    shift = uv.new_tensor([0.5 / width, 0.5 / height])
    return uv * scale + shift
