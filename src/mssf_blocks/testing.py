"""Numerical-check helpers for users' and our own tests.

One tolerance table per dtype, ``assert_close`` that uses it, and a float64 ``gradcheck`` wrapper.
"""

from __future__ import annotations

from typing import Callable, Dict, Sequence, Tuple

import torch
from torch import Tensor

__all__ = ["TOLERANCES", "tolerance", "assert_close", "gradcheck64"]

#: ``dtype -> (rtol, atol)`` used by every numerical comparison in the test suite.
TOLERANCES: Dict[torch.dtype, Tuple[float, float]] = {
    torch.float64: (1e-10, 1e-10),
    torch.float32: (1e-5, 1e-5),
    torch.float16: (1e-3, 1e-3),
    torch.bfloat16: (1e-2, 1e-2),
}


def tolerance(dtype: torch.dtype) -> Tuple[float, float]:
    """``(rtol, atol)`` for ``dtype`` from :data:`TOLERANCES`."""
    if dtype not in TOLERANCES:
        raise KeyError(f"no tolerance for dtype {dtype}; known: {list(TOLERANCES)}")
    return TOLERANCES[dtype]


def assert_close(actual: Tensor, expected: Tensor, dtype: torch.dtype | None = None, msg: str = "") -> None:
    """``torch.testing.assert_close`` with the tolerance of ``dtype`` (default: ``actual.dtype``)."""
    rtol, atol = tolerance(dtype or actual.dtype)
    torch.testing.assert_close(
        actual, expected.to(actual.dtype), rtol=rtol, atol=atol, msg=(lambda m: f"{msg}\n{m}") if msg else None
    )


def gradcheck64(fn: Callable[..., Tensor], inputs: Sequence, **kwargs) -> bool:
    """``torch.autograd.gradcheck`` in float64: floating tensors are cast and marked for gradients.

    Integer and boolean tensors and non-tensors are passed through unchanged. ``kwargs`` go to
    ``gradcheck`` (e.g. ``atol``, ``nondet_tol``).
    """
    cast = []
    for x in inputs:
        if isinstance(x, Tensor) and x.is_floating_point():
            x = x.detach().to(torch.float64).requires_grad_(True)
        cast.append(x)
    kwargs.setdefault("eps", 1e-6)
    kwargs.setdefault("atol", 1e-6)
    return torch.autograd.gradcheck(fn, tuple(cast), **kwargs)
