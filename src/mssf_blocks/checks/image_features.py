"""Checks of the image side of the samplers: the feature levels (count, channels, batch, cameras, dtype)
and the centroid projection a sampler reads."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import INDEX_DTYPES, check_dtype, check_floating, check_index_range, check_shape
from mssf_blocks.checks.agreement import channels_last_hint
from mssf_blocks.errors import MSSFError
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection

__all__ = ["check_image_features"]




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
    check_dtype(batch_index, f"{name}.batch_index", INDEX_DTYPES)
    check_index_range(batch_index, f"{name}.batch_index", batch_size, "image batch size B")
    return uv, valid, batch_index.long()
