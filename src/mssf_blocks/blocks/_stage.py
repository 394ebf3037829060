"""Helpers of :class:`~mssf_blocks.blocks.FusionBlock`: what its spconv parts are given (checked before any
spconv code runs), the camera inputs' batch sizes, the stride of a downsampling stack."""

from __future__ import annotations

from typing import Any, Optional, Tuple

from torch import nn

from mssf_blocks.checks.agreement import level_batch_entries
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import FusionInputs
from mssf_blocks.checks.spconv_inputs import check_spconv_input
from mssf_blocks.sparse_voxels import SparseVoxels

__all__ = ["infer_downsample_stride"]


def _is_spconv_tensor(x: Any) -> bool:
    return all(hasattr(x, a) for a in ("features", "indices", "spatial_shape", "batch_size", "replace_feature"))


def _check_spconv(t: Any, name: str, module: Optional[nn.Module], module_name: str) -> None:
    """The checks of :meth:`SparseVoxels.to_spconv` on ``t`` (SparseVoxels or an spconv tensor), and that
    ``module`` takes its channels and dtype (shapes and dtypes only)."""
    if isinstance(t, SparseVoxels):
        check_spconv_input(t.features, t.coords, t.spatial_shape, t.batch_size, name, module=module,
                           module_name=module_name)
    else:
        check_spconv_input(t.features, t.indices, t.spatial_shape, t.batch_size, name, coords_name="indices",
                           module=module, module_name=module_name)


def _camera_batch(inputs: FusionInputs) -> list:
    """Batch sizes of the camera inputs (agreeing: FusionInputs checked them), for the voxels' one."""
    entries = level_batch_entries(inputs.image_features) + [
        ("lidar2img", inputs.lidar2img.shape[0], tuple(inputs.lidar2img.shape))]
    if inputs.points_to_sensor is not None and inputs.points_to_sensor.dim() == 3:  # (else the projector's shape error)
        entries.append(("points_to_sensor", inputs.points_to_sensor.shape[0], tuple(inputs.points_to_sensor.shape)))
    return entries


def infer_downsample_stride(module: Optional[nn.Module]) -> Tuple[int, int, int]:
    """``(sz, sy, sx)`` stride of a stack of spconv convolutions (product of the strided ones).

    Submanifold convolutions have stride 1. Raises :class:`MSSFError` when ``module`` holds no spconv
    convolution (pass ``downsample_stride`` explicitly) or holds a transposed / inverse one.
    """
    if module is None:
        return (1, 1, 1)
    stride = [1, 1, 1]
    found = False
    for sub in module.modules():
        if not (hasattr(sub, "subm") and hasattr(sub, "stride") and hasattr(sub, "ndim")):
            continue
        found = True
        if getattr(sub, "transposed", False) or getattr(sub, "inverse", False):
            raise MSSFError(
                f"downsample_stride: cannot infer the stride of a transposed/inverse convolution "
                f"({type(sub).__name__}); pass downsample_stride=(sz, sy, sx)"
            )
        if sub.subm:
            continue
        s = sub.stride
        s = [int(s)] * 3 if isinstance(s, int) else [int(v) for v in s]
        if len(s) != 3:
            raise MSSFError(f"downsample_stride: expected a 3D convolution, got stride {sub.stride}")
        stride = [a * b for a, b in zip(stride, s)]
    if not found:
        raise MSSFError(
            f"downsample_stride: could not infer it from downsample ({type(module).__name__} holds no "
            "spconv convolution); pass downsample_stride=(sz, sy, sx)"
        )
    return tuple(stride)
