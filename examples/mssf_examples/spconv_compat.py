"""Make spconv 2.3's backward pass run on CPU-only PyTorch builds.

spconv's ``indice_conv_backward`` asks for the current CUDA stream before it checks whether the
tensors are on the CPU (where it then runs its own gather-matmul-scatter path and never uses the
stream). On a torch build without CUDA that lookup raises "Torch not compiled with CUDA enabled", so
no spconv network can train on CPU. :func:`enable_cpu_backward` replaces the lookup with one that
returns the null stream when CUDA is unavailable; on CUDA builds it changes nothing.

Checked by ``tests/examples/test_spconv_compat.py``: float32 input and weight gradients of
``SparseConv3d`` and ``SubMConv3d`` equal a dense ``conv3d`` reference. (spconv's CPU kernels do not
support float64 correctly, so gradchecks of spconv layers are not meaningful; test them in float32.)
"""

from __future__ import annotations

import torch

__all__ = ["enable_cpu_backward"]

_PATCHED = False


def _stream_or_null() -> int:
    if torch.cuda.is_available():
        return torch.cuda.current_stream().cuda_stream
    return 0


def enable_cpu_backward() -> bool:
    """Patch spconv (idempotent). Returns True when spconv is importable and patched."""
    global _PATCHED
    if _PATCHED:
        return True
    try:
        import spconv.pytorch.ops as ops
    except ImportError:
        return False
    if not torch.cuda.is_available():
        ops.get_current_stream = _stream_or_null
    _PATCHED = True
    return True
