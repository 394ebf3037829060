"""The input checks of multi-scale deformable sampling, run once at each public entry (the op,
``ms_deform_sample``, ``ms_deform_sample_project``); the backends do not check again."""

from __future__ import annotations

from typing import List, Optional, Sequence, Tuple

from torch import Tensor

from mssf_blocks.checks.tensors import (
    INDEX_DTYPES,
    check_dtype,
    check_finite,
    check_floating,
    check_index_range,
    check_shape,
)
from mssf_blocks.errors import MSSFError

__all__ = ["check_projection"]



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
    check_dtype(image_index, "image_index", INDEX_DTYPES)
    check_index_range(image_index, "image_index", dims["I"], "I")
    check_finite(locations, "locations")
    check_finite(weights, "weights")
    return levels, dims


def check_projection(proj_weight: Tensor, proj_bias: Optional[Tensor], levels: List[Tensor], dims: dict) -> None:
    """``proj_weight (M, d, D)`` and ``proj_bias (M, d)`` (or ``None``) against the checked ``dims``."""
    check_shape(proj_weight, "proj_weight", ("M", None, "D"), dims)
    check_dtype(proj_weight, "proj_weight", (levels[0].dtype,), hint=" (must match values)")
    if proj_bias is not None:
        check_shape(proj_bias, "proj_bias", ("M", proj_weight.shape[1]), dims)
        check_dtype(proj_bias, "proj_bias", (levels[0].dtype,), hint=" (must match values)")
