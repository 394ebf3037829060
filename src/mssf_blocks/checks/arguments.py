"""Checks of plain arguments: image sizes ``(H, W)``, angles in radians, ``(x, y, z)`` / ``(z, y, x)``
triples and positive ints. They read no tensor data."""

from __future__ import annotations

import math
from typing import Any, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

__all__ = ["check_image_size", "check_radians", "check_triple", "check_positive_int", "check_point_cloud_range",
           "check_grid_argument"]


# sizes and angles
# --------------------------------------------------------------------------------------------------
def check_image_size(image_size: Any, level_hw: Sequence[int] | None = None, name: str = "image_size",
                     level_name: str = "image_features[0]") -> tuple:
    """``(H, W)`` positive ints; with ``level_hw = (H_0, W_0)`` (the first image level), also that some
    stride ``s`` gives ``|H / s - H_0| <= 1`` and ``|W / s - W_0| <= 1`` (one level-0 pixel each way,
    which allows the rounding of strided convolutions and padding): a swapped ``(W, H)`` fails it."""
    try:
        h, w = (int(v) for v in image_size)
    except (TypeError, ValueError, RuntimeError):
        raise MSSFError(f"{name}: expected (H, W), got {image_size!r}{_per_sample_hint(image_size)}") from None
    if h <= 0 or w <= 0:
        raise MSSFError(f"{name}: expected positive (H, W), got {image_size!r}")
    from mssf_blocks.checks.tensors import is_tracing  # (here: checks.tensors builds on this module)

    if level_hw is not None and not is_tracing():  # (int() of a symbolic level size would specialise a graph)
        h0, w0 = (int(v) for v in level_hw)
        # 1 / s must lie in [(H_0 - 1) / H, (H_0 + 1) / H] and in [(W_0 - 1) / W, (W_0 + 1) / W].
        if max((h0 - 1) / h, (w0 - 1) / w) > min((h0 + 1) / h, (w0 + 1) / w):
            hint = " (swapped? image_size is (H, W))" if (
                max((h0 - 1) / w, (w0 - 1) / h) <= min((h0 + 1) / w, (w0 + 1) / h)) else ""
            raise MSSFError(
                f"{name}: expected (H, W) with the aspect of {level_name} (H_0, W_0) = ({h0}, {w0}) within "
                f"one level-0 pixel, got {(h, w)}{hint}"
            )
    return h, w


def _per_sample_hint(image_size: Any) -> str:
    """Where ``image_size`` holds one ``(H, W)`` per sample (mmdet3d's per-sample ``img_shape``), say what to pass."""
    try:
        rows = [tuple(int(v) for v in row) for row in image_size]
    except (TypeError, ValueError, RuntimeError):
        return ""
    if not rows or any(len(r) != 2 for r in rows):
        return ""
    return (f": {len(rows)} per-sample sizes; pass one (H, W) for the whole batch, the size lidar2img projects "
            f"into (the padded batch input{'' if len(set(rows)) == 1 else ': the samples differ, pad them to one size'})")


def check_radians(angle: Any, name: str) -> float:
    """A finite angle in radians: a magnitude above ``2 pi`` is an angle in degrees (45 for pi / 4)."""
    try:
        a = float(angle)
    except (TypeError, ValueError):
        raise MSSFError(f"{name}: expected an angle in radians (a float), got {angle!r}") from None
    if not math.isfinite(a) or abs(a) > 2 * math.pi + 1e-9:
        raise MSSFError(f"{name}: expected radians with |{name}| <= 2 pi, got {angle!r}: degrees? pass radians "
                        f"(math.radians({angle!r}) = {math.radians(a):.4f})" if math.isfinite(a) else
                        f"{name}: expected a finite angle in radians, got {angle!r}")
    return a


def check_triple(value: Any, name: str, kind: type, positive: bool = False) -> tuple:
    """Turn a length-3 sequence (or tensor) into a tuple of ``kind``, with a clear error."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().tolist()
    try:
        items = list(value)
    except TypeError:
        raise MSSFError(f"{name}: expected a sequence of 3 numbers, got {value!r}") from None
    if len(items) != 3:
        raise MSSFError(f"{name}: expected 3 values, got {len(items)}: {value!r}")
    out = []
    for v in items:
        if kind is int:
            if isinstance(v, bool) or int(v) != v:
                raise MSSFError(f"{name}: expected integers, got {value!r}")
            v = int(v)
        else:
            v = float(v)
            if v != v or v in (float("inf"), float("-inf")):
                raise MSSFError(f"{name}: expected finite values, got {value!r}")
        if positive and v <= 0:
            raise MSSFError(f"{name}: expected positive values, got {value!r}")
        out.append(v)
    return tuple(out)


def check_point_cloud_range(value: Any, name: str = "point_cloud_range") -> Tuple[float, ...]:
    """Six finite numbers ``(x_min, y_min, z_min, x_max, y_max, z_max)`` with max > min (a sequence or a
    tensor), as a tuple of floats."""
    if isinstance(value, Tensor):
        value = value.detach().cpu().tolist()
    try:
        pcr = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        raise MSSFError(f"{name}: expected 6 numbers, got {value!r}") from None
    if len(pcr) != 6 or not all(math.isfinite(x) for x in pcr) or not all(pcr[i + 3] > pcr[i] for i in range(3)):
        raise MSSFError(f"{name}: expected 6 finite numbers (x_min, y_min, z_min, x_max, y_max, z_max) with max > min, "
                        f"got {value!r}")
    return pcr


def check_positive_int(value: Any, name: str, allow_zero: bool = False) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise MSSFError(f"{name}: expected an int, got {type(value).__name__} {value!r}")
    if value < 0 or (value == 0 and not allow_zero):
        raise MSSFError(f"{name}: expected a {'non-negative' if allow_zero else 'positive'} int, got {value}")
    return value


def check_stride2(stride, name: str = "stride") -> Tuple[int, int]:
    """``int`` or ``(sy, sx)`` -> ``(sy, sx)`` positive ints."""
    if isinstance(stride, bool):
        raise MSSFError(f"{name}: expected a positive int or (sy, sx), got {stride!r}")
    if isinstance(stride, int):
        stride = (stride, stride)
    try:
        items = tuple(stride)
    except TypeError:
        raise MSSFError(f"{name}: expected a positive int or (sy, sx), got {stride!r}") from None
    if len(items) != 2 or any(isinstance(s, bool) or not isinstance(s, int) or s <= 0 for s in items):
        raise MSSFError(f"{name}: expected a positive int or (sy, sx) positive ints, got {stride!r}")
    return items


def check_size(size, name: str) -> Tuple[int, int]:
    if not (isinstance(size, (tuple, list, torch.Size)) and len(size) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        raise MSSFError(f"{name}: expected (H, W) positive ints, got {size!r}")
    return int(size[0]), int(size[1])


def check_grid_argument(grid: Any, loose: Any, loose_name: str) -> Any:
    """``grid`` a :class:`~mssf_blocks.VoxelGrid` or ``None``, and not given together with ``loose_name``, the
    loose spelling of what a module reads from it; returns ``grid``."""
    if grid is None:
        return None
    from mssf_blocks.voxel_grid import VoxelGrid  # (voxel_grid builds on checks: imported when used)

    if not isinstance(grid, VoxelGrid):
        raise MSSFError(f"grid: expected a VoxelGrid, got {type(grid).__name__}")
    if loose is not None:
        raise MSSFError(f"{loose_name}: expected either grid= or {loose_name}= (the grid's own value), got both")
    return grid
