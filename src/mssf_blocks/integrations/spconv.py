"""spconv 2.x helpers: CPU backward on CPU-only torch, and quiet calls.

spconv is imported lazily (inside the functions), so this module imports without it.

**CPU backward.** spconv 2.3's ``indice_conv_backward`` asks for the current CUDA stream before it
looks at the tensors' device (on the CPU it then runs its own gather-matmul-scatter path and never
uses the stream). On a torch build without CUDA that lookup raises "Torch not compiled with CUDA
enabled", so no spconv network can train on a CPU-only torch. :func:`enable_cpu_backward` replaces
the lookup with one that returns the null stream when CUDA is unavailable; on CUDA builds it changes
nothing. (With it, spconv 2.3.8's CPU ``SubMConv3d`` / ``SparseConv3d`` equal a dense ``conv3d`` in float32
and float64, with or without bias, forward and backward: ``tests/integrations/test_spconv_dense_reference.py``.)

**Quiet calls.** Two messages come from spconv's own code, not from the caller's: torch.fx logs
"is_fx_tracing will return true ..." (once per process) when spconv's ``SparseConvTensor`` metaclass
asks ``torch.fx`` whether it is tracing, and spconv's ``scatter_nd`` (``SparseConvTensor.dense()``)
indexes with a list, which torch >= 2.x warns about ("Using a non-tuple sequence for multidimensional
indexing"). :func:`quiet` drops exactly these two inside a ``with`` block (nothing else, nothing
outside it); :func:`dense` is ``SparseConvTensor.dense()`` written with tuple indexing.

Checked by ``tests/integrations/test_spconv.py`` (gradients equal a dense ``conv3d`` reference; the two
messages appear without :func:`quiet` and not with it).
"""

from __future__ import annotations

import contextlib
import logging
import warnings
from typing import Any, Iterator

import torch
from torch import Tensor

__all__ = ["enable_cpu_backward", "quiet", "dense"]

_PATCHED = False

#: The logger torch.fx uses for its one-time ``is_fx_tracing`` message.
_FX_LOGGER = "torch.fx._symbolic_trace"
_FX_MESSAGE = "is_fx_tracing will return true"
_INDEXING_MESSAGE = "Using a non-tuple sequence for multidimensional indexing"


def _stream_or_null() -> int:
    if torch.cuda.is_available():
        return torch.cuda.current_stream().cuda_stream
    return 0


def enable_cpu_backward() -> bool:
    """Let spconv run backward on a CPU-only torch (idempotent).

    Returns True when spconv is importable (patched where needed), False when it is not installed.
    Call it once before the first backward pass, e.g. at the start of a training script.
    """
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


class _DropFxTracingMessage(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_FX_MESSAGE)


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Drop spconv's two spurious messages (see the module docstring) inside the block only.

    The filters are the narrowest that match: one log message of one torch.fx logger, and one
    ``UserWarning`` text raised from spconv's modules. Other warnings and log records pass.
    """
    logger = logging.getLogger(_FX_LOGGER)
    flt = _DropFxTracingMessage()
    logger.addFilter(flt)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=_INDEXING_MESSAGE, category=UserWarning, module=r"spconv\.")
            yield
    finally:
        logger.removeFilter(flt)


def dense(x: Any, channels_first: bool = True) -> Tensor:
    """``x.dense(channels_first)`` of an spconv ``SparseConvTensor``, without spconv's list indexing.

    Returns ``(B, C, *spatial_shape)`` (``channels_first``) or ``(B, *spatial_shape, C)``; voxels
    absent from ``x`` are zero. Same values and gradients as ``x.dense()``.
    """
    feats, idx = x.features, x.indices.to(x.features.device).long()
    shape = [int(x.batch_size), *(int(s) for s in x.spatial_shape), feats.shape[1]]
    out = feats.new_zeros(shape)
    out[tuple(idx.unbind(1))] = feats
    if not channels_first:
        return out
    return out.movedim(-1, 1).contiguous()
