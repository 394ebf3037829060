"""Input validation shared by every function and module.

One place that turns a wrong shape, dtype or value into an :class:`MSSFError` whose message names the
argument, what was expected and what was received.

Graph capture (``torch.compile``, ``torch.export``, ``torch.jit.trace``, ``torch.onnx.export``): checks
of tensor *values* (finite entries, index ranges) read data, i.e. synchronise with the device and, while
a graph is being captured, break it, guard on the data or crash the tracer. Every such check is a
:func:`value_check`: it runs eagerly and is skipped while :func:`is_tracing` (the captured graph then
contains no check at all, so it costs nothing there). Shape, dtype and type checks stay: they read no
data and run once at capture time on the (symbolic) shapes. See ``docs/conventions.md``.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Mapping, MutableMapping, Sequence, TypeVar, Union

import torch
from torch import Tensor

from .errors import MSSFError

Dim = Union[int, str, None]
_F = TypeVar("_F", bound=Callable[..., Any])


def is_tracing() -> bool:
    """Whether a graph is being captured: ``torch.compile`` / ``torch.export`` (dynamo or non-strict),
    ``torch.jit.trace`` or the ONNX exporters. Value checks are skipped then; the fusion modules also take
    their static-shape path (``docs/deployment.md``)."""
    compiler = getattr(torch, "compiler", None)
    if compiler is not None:
        # (is_compiling is constant-folded by dynamo, so this costs nothing in a compiled graph)
        if compiler.is_compiling() or (hasattr(compiler, "is_exporting") and compiler.is_exporting()):
            return True
    if torch.jit.is_tracing():
        return True
    onnx = getattr(torch, "onnx", None)
    return bool(onnx is not None and onnx.is_in_onnx_export())


try:  # (private, hence guarded) FakeTensors carry no data: torch.export builds its inputs' dataclasses
    from torch._subclasses.fake_tensor import is_fake as _is_fake  # from them before is_exporting() is set
except ImportError:  # pragma: no cover - depends on the torch version
    def _is_fake(x: Any) -> bool:
        return False


def _has_no_data(x: Any) -> bool:
    return isinstance(x, Tensor) and _is_fake(x)


def value_check(fn: _F) -> _F:
    """Mark a check that reads tensor values: it runs eagerly and is skipped while :func:`is_tracing`.

    The decorated check returns its first argument in both cases, so ``x = check(x, ...)`` keeps working.
    Every check of data (not of shapes or dtypes) in the library is written through this decorator.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if is_tracing() or (args and _has_no_data(args[0])):
            return args[0] if args else None
        return fn(*args, **kwargs)

    return wrapper  # type: ignore[return-value]


def _fmt_spec(spec: Sequence[Dim], dims: Mapping[str, int]) -> str:
    parts = []
    for d in spec:
        if d is None:
            parts.append("*")
        elif isinstance(d, str) and d in dims:
            parts.append(f"{d}={dims[d]}")
        else:
            parts.append(str(d))
    return "(" + ", ".join(parts) + ("," if len(parts) == 1 else "") + ")"


def check_tensor(x: Any, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise MSSFError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def check_shape(
    x: Any,
    name: str,
    spec: Sequence[Dim],
    dims: MutableMapping[str, int] | None = None,
) -> Tensor:
    """Check ``x`` against a shape spec with named dimensions.

    Args:
        x: the tensor.
        name: the argument name used in the error message.
        spec: one entry per dimension: an ``int`` (exact size), a ``str`` (a named size that must agree
            with every other use of the same name in ``dims``) or ``None`` (any size).
        dims: named sizes bound so far; new names are bound here (so several arguments can be checked
            against each other).

    Raises:
        MSSFError: naming ``name``, the expected shape (with bound sizes) and the received shape.
    """
    x = check_tensor(x, name)
    dims = {} if dims is None else dims
    if x.dim() != len(spec):
        raise MSSFError(
            f"{name}: expected a {len(spec)}-d tensor of shape {_fmt_spec(spec, dims)}, "
            f"got shape {tuple(x.shape)}"
        )
    for size, d in zip(x.shape, spec):
        if d is None:
            continue
        if isinstance(d, (int, torch.SymInt)):  # (a SymInt: a size read from another tensor under export)
            if size != d:
                raise MSSFError(
                    f"{name}: expected shape {_fmt_spec(spec, dims)}, got shape {tuple(x.shape)}"
                )
        else:
            if d in dims and dims[d] != size:
                raise MSSFError(
                    f"{name}: expected shape {_fmt_spec(spec, dims)}, got shape {tuple(x.shape)} "
                    f"({d} disagrees with another argument)"
                )
            # (the size itself, not int(size): under torch.compile(dynamic=True) it is symbolic and int()
            # would specialise the graph to this voxel count)
            dims.setdefault(d, size)
    return x


def check_floating(x: Tensor, name: str) -> Tensor:
    if not x.is_floating_point():
        raise MSSFError(f"{name}: expected a floating-point tensor, got dtype {x.dtype}")
    return x


def check_dtype(x: Tensor, name: str, dtypes: Sequence[torch.dtype], hint: str = "") -> Tensor:
    if x.dtype not in dtypes:
        names = " or ".join(str(d) for d in dtypes)
        raise MSSFError(f"{name}: expected dtype {names}, got {x.dtype}{hint}")
    return x


def autocast_on(device_type: str) -> bool:
    """Whether ``torch.autocast`` is enabled for ``device_type`` (``"cpu"``, ``"cuda"``, ...)."""
    try:
        return bool(torch.is_autocast_enabled(device_type))
    except TypeError:  # torch < 2.4 has no device argument
        if device_type == "cpu":
            return bool(torch.is_autocast_cpu_enabled())
        return bool(torch.is_autocast_enabled())


@value_check
def check_finite(x: Tensor, name: str) -> Tensor:
    if x.is_floating_point() and x.numel() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise MSSFError(f"{name}: expected finite values, got {bad} NaN/inf entries")
    return x


@value_check
def check_index_ranges(checks) -> None:
    """:func:`check_index_range` for several ``(x, name, upper, upper_name)`` at once, with one host
    synchronisation for all of them (each ``min`` / ``max`` read back stalls a GPU); same messages."""
    checks = [c for c in checks if c[0].numel()]
    if not checks:
        return
    bounds = torch.stack([t for c in checks for t in (c[0].min().long(), c[0].max().long())]).tolist()
    for i, (_, name, upper, upper_name) in enumerate(checks):
        lo, hi = bounds[2 * i], bounds[2 * i + 1]
        if lo < 0 or hi >= upper:
            raise MSSFError(
                f"{name}: expected values in [0, {upper}) ({upper_name}={upper}), got values in [{lo}, {hi}]"
            )


@value_check
def check_index_range(x: Tensor, name: str, upper: int, upper_name: str) -> Tensor:
    """Integer tensor with every entry in ``[0, upper)``."""
    if x.numel():
        lo, hi = int(x.min()), int(x.max())
        if lo < 0 or hi >= upper:
            raise MSSFError(
                f"{name}: expected values in [0, {upper}) ({upper_name}={upper}), "
                f"got values in [{lo}, {hi}]"
            )
    return x


@value_check
def check_nonnegative(x: Tensor, name: str, what: str = "indices") -> Tensor:
    """Integer tensor with every entry ``>= 0``."""
    if x.numel():
        lo = int(x.min())
        if lo < 0:
            raise MSSFError(f"{name}: expected non-negative {what}, got min {lo}")
    return x


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


def check_positive_int(value: Any, name: str, allow_zero: bool = False) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise MSSFError(f"{name}: expected an int, got {type(value).__name__} {value!r}")
    if value < 0 or (value == 0 and not allow_zero):
        raise MSSFError(f"{name}: expected a {'non-negative' if allow_zero else 'positive'} int, got {value}")
    return value
