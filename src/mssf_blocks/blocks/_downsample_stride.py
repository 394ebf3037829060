"""The stride of a fusion block's downsampling stack (the product of its strided spconv convolutions)."""

from __future__ import annotations

from typing import Optional, Tuple

from torch import nn

from mssf_blocks.errors import MSSFError

__all__ = ["infer_downsample_stride"]


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
