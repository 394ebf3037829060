"""Validation, dtype and output-stage helpers shared by the image samplers (SFF, MSDFF, QueryInit)."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple, Type

import torch
from torch import Tensor, nn

from ._checks import autocast_off, check_dtype, convert_up, check_floating, check_index_range, check_shape
from ._consistency import batch_norm_in_training, channels_last_hint, check_batch_statistics
from ._sanity import geometry_checks_enabled
from ._static import use_static_path
from .errors import MSSFError
from .functional.static import linear_norm_visible_static
from .geometry import CentroidProjection

__all__ = ["check_image_features"]

_INT_DTYPES = (torch.int32, torch.int64)


def check_image_features(
    image_features: Sequence[Tensor],
    name: str = "image_features",
    num_levels: Optional[int] = None,
    channels: Optional[Sequence[int]] = None,
    batch_size: Optional[int] = None,
    num_cameras: Optional[int] = None,
    channels_name: Optional[str] = None,
) -> List[Tensor]:
    """Validate multi-scale image features and return them as ``(B, V, C_l, H_l, W_l)`` views.

    Args:
        image_features: ``L`` levels, each ``(B, C_l, H_l, W_l)`` (V = 1) or ``(B, V, C_l, H_l, W_l)``.
        name: argument name used in error messages (``image_features[l]`` names a level).
        num_levels: expected ``L`` (``None``: any ``L >= 1``).
        channels: expected ``C_l`` of every level.
        batch_size: expected ``B``.
        num_cameras: expected ``V``.
        channels_name: the constructor argument ``channels`` come from, named when a level's channels
            differ (``"SFF in_channels[{l}]"``, ``{l}`` the level).

    Returns:
        The levels as 5-d ``(B, V, C_l, H_l, W_l)`` tensors (views, no copy).

    Raises:
        MSSFError: naming the level, the expected and the received shape.
    """
    if isinstance(image_features, Tensor) or not isinstance(image_features, Sequence):
        raise MSSFError(
            f"{name}: expected a sequence (list/tuple) of level tensors (B, C_l, H_l, W_l) or "
            f"(B, V, C_l, H_l, W_l), got {type(image_features).__name__}"
            + (f" of shape {tuple(image_features.shape)} (wrap a single level in a list)"
               if isinstance(image_features, Tensor) else "")
        )
    if len(image_features) == 0:
        raise MSSFError(f"{name}: expected at least one level, got an empty sequence")
    if num_levels is not None and len(image_features) != num_levels:
        owner = f"{channels_name.split()[0]} num_levels" if channels_name else "num_levels"
        raise MSSFError(f"{name}: expected {num_levels} levels ({owner}={num_levels}), got {len(image_features)}")
    if channels is not None and len(channels) != len(image_features):
        owner = f" ({channels_name.split('[')[0]}={tuple(channels)})" if channels_name else ""
        raise MSSFError(
            f"{name}: expected {len(channels)} levels with channels {tuple(channels)}{owner}, "
            f"got {len(image_features)} levels"
        )
    dims = {}
    if batch_size is not None:
        dims["B"] = int(batch_size)
    if num_cameras is not None:
        dims["V"] = int(num_cameras)
    out = []
    dtype = None
    for l, level in enumerate(image_features):
        lname = f"{name}[{l}]"
        if not isinstance(level, Tensor):
            raise MSSFError(f"{lname}: expected a torch.Tensor, got {type(level).__name__}")
        c = None if channels is None else int(channels[l])
        if level.dim() == 4:
            v = dims.get("V", 1)
            if v != 1:  # (before the batch size: a (B*V, C, H, W) level would be blamed for its batch)
                b = dims.get("B")
                folded = (f"; a (B*V, C, H, W) level: {lname}.view({b}, {v}, *{lname}.shape[1:])"
                          if b is not None and level.shape[0] == b * v else "")
                raise MSSFError(
                    f"{lname}: a 4-d level (B, C, H, W) means one camera, but V={v} "
                    f"(from lidar2img or another level); pass (B, V, C, H, W), got shape {tuple(level.shape)}{folded}"
                )
            _check_level_shape(level, lname, ("B", c, None, None), dims, channels_name, l)
            dims["V"] = 1
            level = level[:, None]
        elif level.dim() == 5:
            _check_level_shape(level, lname, ("B", "V", c, None, None), dims, channels_name, l)
        else:
            raise MSSFError(
                f"{lname}: expected shape (B, C_l, H_l, W_l) or (B, V, C_l, H_l, W_l), "
                f"got shape {tuple(level.shape)}"
            )
        check_floating(level, lname)
        if level.shape[-1] == 0 or level.shape[-2] == 0:
            raise MSSFError(f"{lname}: expected a non-empty feature map, got shape {tuple(level.shape)}")
        if dtype is None:
            dtype = level.dtype
        elif level.dtype != dtype:
            raise MSSFError(f"{lname}: expected dtype {dtype} (as {name}[0]), got {level.dtype}")
        out.append(level)
    return out


def _check_level_shape(level: Tensor, lname: str, spec: tuple, dims: dict, channels_name: Optional[str], l: int) -> None:
    """:func:`check_shape`; a wrong channel count also names the constructor argument it disagrees with."""
    try:
        check_shape(level, lname, spec, dims)
    except MSSFError as exc:
        c, got = spec[-3], level.shape[-3]
        if channels_name is None or c is None or got == c:
            raise
        arg = channels_name.format(l=l)
        fix = f"build it with {arg.split()[-1]}={got}, or pass {c}-channel levels" + channels_last_hint(level, c, lname)
        raise MSSFError(f"{exc}: {got} channels, but {arg}={c}; {fix}") from None


def _check_projection(projection: CentroidProjection, batch_size: int, num_cameras: int,
                      name: str = "projection") -> Tuple[Tensor, Tensor, Tensor]:
    for attr in ("uv", "valid", "batch_index"):
        if not hasattr(projection, attr):
            raise MSSFError(
                f"{name}: expected a CentroidProjection (with .{attr}), got {type(projection).__name__}"
            )
    dims = {"V": num_cameras}
    uv = check_shape(projection.uv, f"{name}.uv", ("N", "V", 2), dims)
    check_floating(uv, f"{name}.uv")
    valid = check_shape(projection.valid, f"{name}.valid", ("N", "V"), dims)
    check_dtype(valid, f"{name}.valid", (torch.bool,))
    batch_index = check_shape(projection.batch_index, f"{name}.batch_index", ("N",), dims)
    check_dtype(batch_index, f"{name}.batch_index", _INT_DTYPES)
    check_index_range(batch_index, f"{name}.batch_index", batch_size, "image batch size B")
    return uv, valid, batch_index.long()


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


def check_visible_rows(norm: nn.Module, rows: int, n: int) -> None:
    """Our error, not BatchNorm's, for one visible voxel in training mode (the count is on the host already:
    ``nonzero`` read it). Every sampler's output stage goes through it."""
    check_batch_statistics(norm, rows, "projection", f"exactly one of the {n} voxels is visible in the image",
                           "fusion block")


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
