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
from typing import Any, Callable, Mapping, MutableMapping, Optional, Sequence, Tuple, TypeVar, Union

import torch
from torch import Tensor

from mssf_blocks import torch_versions
from mssf_blocks.checks.arguments import check_positive_int, check_triple
from mssf_blocks.errors import MSSFError

Dim = Union[int, str, None]
_F = TypeVar("_F", bound=Callable[..., Any])
#: the integer dtypes index tensors may have (batch indices, voxel coordinates)
INDEX_DTYPES = (torch.int32, torch.int64)


def is_tracing() -> bool:
    """Whether a graph is being captured: ``torch.compile`` / ``torch.export`` (dynamo or non-strict),
    ``torch.jit.trace`` or the ONNX exporters. Value checks are skipped then; the fusion modules also take
    their static-shape path (``docs/deployment.md``)."""
    # (is_compiling is constant-folded by dynamo, so this costs nothing in a compiled graph)
    if torch_versions.is_compiling() or torch_versions.is_exporting():
        return True
    if torch.jit.is_tracing():
        return True
    onnx = getattr(torch, "onnx", None)
    return bool(onnx is not None and onnx.is_in_onnx_export())


# FakeTensors carry no data: torch.export builds its inputs' dataclasses from them before is_exporting()
_is_fake = torch_versions.is_fake


def _has_no_data(x: Any) -> bool:
    """A FakeTensor, or a list / tuple (of tuples) holding one (e.g. ``check_index_ranges``' checks)."""
    if isinstance(x, Tensor):
        return _is_fake(x)
    if isinstance(x, (list, tuple)):
        return any(_has_no_data(item) for item in x[:8])
    return False


def value_check(fn: _F) -> _F:
    """Mark a check that reads tensor values: it runs eagerly and is skipped while :func:`is_tracing`.

    The decorated check returns its first argument in both cases, so ``x = check(x, ...)`` keeps working.
    Every check of data (not of shapes or dtypes) in the library is written through this decorator.
    """

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        if is_tracing() or _has_no_data(args):
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
    return torch_versions.autocast_enabled(device_type)


def autocast_off(device_type: str):
    """A context that disables autocast for ``device_type`` when it is on (else does nothing).

    Geometry (projection, centroids, sampling locations) runs inside it: autocast would round its
    matrix products to bfloat16 / float16, pixels off by several pixels at 50 m.
    """
    return torch_versions.autocast_off(device_type)


@value_check
def check_finite(x: Tensor, name: str) -> Tensor:
    # A NaN or inf entry makes the sum NaN or inf, so a finite sum proves every entry finite: one
    # reduction instead of abs, compare and reduce (6.7 -> 0.24 ms on the 15 MiB of locations and
    # weights of 8,000 MSDFF queries, one thread). Only a non-finite sum (a bad entry, or finite
    # entries overflowing) takes the exact test.
    if x.is_floating_point() and x.numel() and not bool(torch.isfinite(x.sum())) and not bool(torch.isfinite(x).all()):
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
        lo, hi = torch.stack([x.min(), x.max()]).tolist()  # one host synchronisation, not two
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


@value_check
def check_voxel_coords(coords: Tensor, spatial_shape: Sequence[int], batch_size: int, name: str = "coords") -> Tensor:
    """``(N, 4)`` ``(batch, z, y, x)`` rows inside ``[0, batch_size) x [0, D) x [0, H) x [0, W)``.

    The error names the column and its bound, as :class:`~mssf_blocks.sparse_voxels.SparseVoxels` does. Two
    reductions over ``coords`` (not one per column).
    """
    if coords.numel():
        lows, highs = coords.amin(0).tolist(), coords.amax(0).tolist()
        bounds = [(batch_size, "batch_size", "batch index")] + [
            (int(spatial_shape[a]), f"spatial_shape[{a}]", f"{axis} index") for a, axis in enumerate("zyx")
        ]
        for col, ((upper, upper_name, what), lo, hi) in enumerate(zip(bounds, lows, highs)):
            if lo < 0 or hi >= upper:
                raise MSSFError(
                    f"{name}[:, {col}] ({what}): expected values in [0, {upper}) ({upper_name}={upper}), "
                    f"got values in [{lo}, {hi}]"
                )
    return coords


def check_points(
    points: Any, points_batch: Any, exact_xyz: bool = False, name: str = "points", batch_name: str = "points_batch",
    rows: str = "P",
) -> Tensor:
    """Raw points ``(P, 3)`` (``exact_xyz``) or ``(P, 3+)`` with x, y, z first, and ``points_batch (P,)``.

    A transposed ``(3, P)`` array is blamed on ``points`` (not on ``points_batch``'s length); with
    ``exact_xyz`` extra columns are refused with how to slice them (OpenPCDet's ``batch_dict["points"]``
    is ``(b, x, y, z, ...)``: taking its first three columns as x, y, z would silently be wrong).
    """
    check_tensor(points, name)
    expected = f"({rows}, 3)" if exact_xyz else f"({rows}, >=3) with x, y, z first"
    if points.dim() != 2:
        raise MSSFError(f"{name}: expected a 2-d tensor of shape {expected}, got shape {tuple(points.shape)}")
    p, c = points.shape
    n_batch = points_batch.shape[0] if isinstance(points_batch, Tensor) and points_batch.dim() == 1 else None
    if c != 3 and p == 3 and (n_batch is None or n_batch == c):
        raise MSSFError(
            f"{name}: expected shape {expected} (one row per point), got shape {tuple(points.shape)}; "
            f"transposed? pass {name}.T"
        )
    if c < 3:
        raise MSSFError(f"{name}: expected shape {expected}, got shape {tuple(points.shape)}")
    if exact_xyz and c != 3:
        raise MSSFError(
            f"{name}: expected shape {expected}, got shape {tuple(points.shape)}; slice the coordinates: "
            f"{name}[:, :3] for (x, y, z, features...) rows, or for OpenPCDet's batch_dict['points'] "
            f"(b, x, y, z, ...) {name}=pts[:, 1:4] and {batch_name}=pts[:, 0].long()"
        )
    check_floating(points, name)
    check_shape(points_batch, batch_name, (p,))
    if not exact_xyz and c >= 4:  # (a batch-index column read as x; _sanity imports this module)
        from mssf_blocks.checks.geometry import check_batch_column
        check_batch_column(points, points_batch, name, batch_name)
    return points


def to_module_dtype(x: Any, name: str, dtype: torch.dtype, owner: str) -> Tensor:
    """``x`` in the dtype of ``owner``'s parameters, by the library's one dtype rule
    (``docs/conventions.md``, "Dtypes").

    Lower or equal precision is converted (float16 / bfloat16 into float32, float32 into float64,
    float32 into a half-precision module); a float64 ``x`` into a module whose parameters are not
    float64 is refused: a float64 input means a float64 check, which silent rounding would defeat.
    """
    x = check_floating(check_tensor(x, name), name)
    return convert_up(x, dtype, name, f"the dtype of {owner}'s parameters")


def convert_up(x: Tensor, dtype: torch.dtype, name: str, what: str) -> Tensor:
    """The dtype rule on a floating ``x``: ``x`` itself if already ``dtype``, refused (naming ``what``
    ``dtype`` is) if float64 for another ``dtype``, else converted."""
    if x.dtype == dtype:
        return x
    if x.dtype == torch.float64:
        raise MSSFError(
            f"{name}: expected dtype {dtype} or lower precision ({what}), got "
            f"torch.float64; convert the module with .double() or the tensor with .to({dtype})"
        )
    return x.to(dtype)




# --------------------------------------------------------------------------------------------------
# sparse tensors: a SparseVoxels' fields, voxel_centroids' inputs (one call each: the data stays here)
# --------------------------------------------------------------------------------------------------
def _permutation_hint(coords: Tensor, spatial_shape: Tuple[int, int, int]) -> str:
    """Where the coordinates fit a permutation of ``spatial_shape`` (e.g. ``(W, H, D)`` given), say so."""
    import itertools

    if int(coords[:, 1:].amin()) < 0:
        return ""
    top = [int(v) + 1 for v in coords[:, 1:].amax(0).tolist()]  # (z, y, x) extents needed
    candidates = [tuple(spatial_shape)[::-1]] + list(itertools.permutations(spatial_shape))  # (W, H, D) first
    fits = [p for p in candidates
            if p != tuple(spatial_shape) and all(t <= s for t, s in zip(top, p))]
    if not fits:
        return ""
    return (f"; the coordinates fit spatial_shape={fits[0]}: spatial_shape is (D, H, W) = (z, y, x) cells, "
            f"given in another axis order (e.g. (W, H, D))?")


def check_voxel_features(features: Tensor, n: int, name: str = "features") -> Tensor:
    """``(n, C)`` floating-point features of ``n`` voxels."""
    check_shape(features, name, (n, None))
    return check_floating(features, name)


def check_voxel_tensors(features: Tensor, coords: Tensor, spatial_shape: Sequence[int], batch_size: int) -> None:
    """A sparse tensor's ``coords (N, 4)`` int32 ``(batch, z, y, x)`` inside ``[0, batch_size) x spatial_shape``
    and ``features (N, C)`` floating; a range error names a permuted ``spatial_shape`` that would fit."""
    check_shape(coords, "coords", ("N", 4))
    check_dtype(coords, "coords", (torch.int32,), hint=" (convert with coords.int())")
    if coords.numel():
        # one host synchronisation for the four range checks, not eight (a GPU stalls on each)
        try:
            check_index_ranges(
                [(coords[:, 0], "coords[:, 0] (batch index)", batch_size, "batch_size")]
                + [(coords[:, a], f"coords[:, {a}] ({n} index)", spatial_shape[a - 1],
                    f"spatial_shape[{a - 1}]") for a, n in zip((1, 2, 3), ("z", "y", "x"))]
            )
        except MSSFError as exc:  # (the error path only: one more read, to name a permuted spatial_shape)
            raise MSSFError(f"{exc}{_permutation_hint(coords, spatial_shape)}") from None
    check_voxel_features(features, coords.shape[0])


def check_centroid_inputs(points, points_batch, coords, spatial_shape, batch_size, stride, voxel_size,
                          point_range_min, point_range_max):
    """The inputs of :func:`~mssf_blocks.functional.geometry.voxel_centroids`, normalised: returns
    ``(spatial_shape, batch_size, stride, voxel_size, point_range_min, point_range_max)``."""
    check_points(points, points_batch)
    check_finite(points[:, :3], "points[:, :3]")
    check_dtype(points_batch, "points_batch", INDEX_DTYPES)
    check_shape(coords, "coords", ("N", 4))
    check_dtype(coords, "coords", INDEX_DTYPES)
    spatial_shape = check_triple(spatial_shape, "spatial_shape", int, positive=True)
    batch_size = check_positive_int(batch_size, "batch_size")
    check_index_range(points_batch, "points_batch", batch_size, "batch_size")
    # A coordinate outside the grid would alias another voxel's key (x == W is the next row's x == 0;
    # x == -1 collides with the key of out-of-range points).
    check_voxel_coords(coords, spatial_shape, batch_size)
    stride = check_triple(stride, "stride", int, positive=True)
    voxel_size = check_triple(voxel_size, "voxel_size", float, positive=True)
    point_range_min = check_triple(point_range_min, "point_range_min", float)
    if point_range_max is not None:
        point_range_max = check_triple(point_range_max, "point_range_max", float)
        if any(h <= l for h, l in zip(point_range_max, point_range_min)):
            raise MSSFError(
                f"point_range_max: expected every value above point_range_min {point_range_min}, "
                f"got {point_range_max}"
            )
    if coords.device != points.device or points_batch.device != points.device:
        raise MSSFError(
            f"points, points_batch, coords: expected one device, got {points.device}, "
            f"{points_batch.device}, {coords.device}"
        )
    return spatial_shape, batch_size, stride, voxel_size, point_range_min, point_range_max


def check_coords(coords: Tensor, n: Optional[int] = None) -> Tensor:
    check_shape(coords, "coords", ("N" if n is None else n, 4))
    check_dtype(coords, "coords", INDEX_DTYPES, hint=" ((batch, z, y, x) integer indices)")
    return check_nonnegative(coords, "coords", "(batch, z, y, x) indices")
