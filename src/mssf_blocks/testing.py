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


def _precision_rank(dtype: torch.dtype) -> float:
    """The relative tolerance of ``dtype``: larger is less precise."""
    return tolerance(dtype)[0]


def assert_close(actual: Tensor, expected: Tensor, dtype: torch.dtype | None = None, msg: str = "") -> None:
    """``torch.testing.assert_close`` with the tolerance of the less precise of the two dtypes.

    Integer and bool tensors (both of them) are compared exactly. With a floating tensor on either
    side, the tolerance is that of ``dtype`` when given, else of the less precise floating dtype of
    ``actual`` and ``expected`` (a float32 result against a float64 reference is held to float32's
    tolerance, whichever side it is on); both are compared in float64, so neither is rounded to the
    other's dtype first. The failure message names both dtypes and the tolerance used.
    """
    for name, x in (("actual", actual), ("expected", expected)):
        if not isinstance(x, Tensor):
            raise TypeError(f"assert_close: {name}: expected a torch.Tensor, got {type(x).__name__}")
    pair = f"actual dtype {actual.dtype}, expected dtype {expected.dtype}"
    floating = [x.dtype for x in (actual, expected) if x.is_floating_point()]
    if dtype is None and not floating:  # int / bool on both sides: exact
        rtol, atol, what = 0.0, 0.0, "exact (integer / bool)"
        a, e = actual, expected.to(actual.dtype) if actual.dtype != expected.dtype else expected
        if actual.dtype == torch.bool or expected.dtype == torch.bool:
            a, e = actual.long(), expected.long()
    else:
        used = dtype if dtype is not None else max(floating, key=_precision_rank)
        rtol, atol = tolerance(used)
        what = f"tolerance of {used} (rtol={rtol}, atol={atol})"
        a, e = actual.to(torch.float64), expected.to(torch.float64)
    head = f"{msg}\n" if msg else ""
    torch.testing.assert_close(
        a, e, rtol=rtol, atol=atol, msg=lambda m: f"{head}{m}\n({pair}; compared with the {what})"
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
