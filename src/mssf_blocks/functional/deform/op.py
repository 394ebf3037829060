"""The one sampling op: MSDFF's multi-scale deformable sampling with value projection, every device.

``out[q, m] = sum_{l, p} weights[q, m, l, p] * bilinear(W_m @ values[l][image_index[q], 0] + b_m, locations[q, m, l, p])``

(:func:`~mssf_blocks.functional.ms_deform_sample_project`'s formula, zero padding, ``align_corners=False``)
registered with ``torch.library`` as ``torch.ops.mssf_blocks.deform_sample_project``: a custom op with
a fake (meta) implementation and an autograd formula, so ``torch.compile`` and ``torch.export`` see one
opaque node. Inputs are checked once, here, at the entry :func:`deform_sample_project`; the backends
are not re-checked. Backends, one place each:

* ``"touched"``: the CPU plans (:mod:`~mssf_blocks.functional.deform.touched`, costs in ``plan_costs.py``);
* ``"grid"``: project every pixel, one ``F.grid_sample`` per level (:mod:`~mssf_blocks.functional.deform.grid`);
* ``"triton"``: project every pixel, the Triton kernels (:mod:`~mssf_blocks.functional.deform.triton`).

Which serves which device is :data:`~mssf_blocks.functional.plan_costs.SAMPLING_BACKENDS`; an argument
(``backend=``) or the environment variable ``MSSF_SAMPLING_BACKEND`` forces one. A triton older than
``plan_costs.TRITON_MIN_VERSION`` is never tried (the grid path serves from the first call, no warning). A
Triton compile or launch failure on a GPU warns once, naming the cause, and the grid path serves from then on.

The op's backward is a second op. For ``"triton"`` it runs the backward kernel; the other backends
differentiate their forward under autograd inside it (a custom op's implementation runs without
autograd). Under ``torch.compile`` with gradients, a third op, ``deform_sample_project_keep``, runs
that forward once, under autograd, and keeps its graph for the backward (``kept.py``); the plain op's
backward runs the forward again. So that eager training does neither, the entry calls the
``"touched"`` and ``"grid"`` code directly (same code, same numbers, native autograd) unless a graph
is being captured. Inside the registered ops the CPU plans first leave out the queries that read no
pixel (MSDFF's static layout puts its invalid pairs at ``uv = -1``).
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import warnings
from typing import List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks import torch_versions
from mssf_blocks.checks.tensors import is_tracing
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.plan_costs import SAMPLING_BACKENDS, SAMPLING_FALLBACK, TRITON_MIN_VERSION
from mssf_blocks.functional.deform import grid, kept, touched
from mssf_blocks.checks.deform import _check_deform_inputs, check_projection
from mssf_blocks.functional.deform.triton import installed_version as _triton_version

__all__ = ["deform_sample_project", "sample_project_unchecked", "resolve_backend", "BACKENDS", "ENV_VAR", "TRITON_MAX_HEAD_DIM"]

BACKENDS = ("touched", "grid", "triton")
ENV_VAR = "MSSF_SAMPLING_BACKEND"
#: Widest head ``d`` the Triton kernels take (their compile test covers up to it; wider: the grid path).
TRITON_MAX_HEAD_DIM = 256
_TRITON_DTYPES = (torch.float32, torch.bfloat16, torch.float16)
try:  # (looked up once, at import: no import of triton, and nothing to trace under torch.compile)
    _HAS_TRITON = importlib.util.find_spec("triton") is not None
except (ImportError, ValueError):  # e.g. an import hook that blocks it
    _HAS_TRITON = False
_TRITON_FAILURE: List[str] = []  # the cause, once a launch failed on a GPU (the grid path serves since)
_TRITON_VERSION = _triton_version() if _HAS_TRITON else None  # (looked up once, like _HAS_TRITON)


# ---------------------------------------------------------------------------------------------------
# backend choice
# ---------------------------------------------------------------------------------------------------
def _triton_unusable(device_type: str, dtype: torch.dtype, head_dim: int) -> Optional[str]:
    """Why the Triton kernels cannot serve these inputs, or ``None``."""
    if device_type == "cpu" and os.environ.get("TRITON_INTERPRET") != "1":
        return "CPU tensors need Triton's interpreter (TRITON_INTERPRET=1 set before triton is imported)"
    if device_type not in ("cpu", "cuda"):
        return f"the kernels run on CUDA devices, got {device_type!r} tensors"
    if dtype not in _TRITON_DTYPES:
        return f"the kernels take {[str(t) for t in _TRITON_DTYPES]}, got {dtype}"
    if head_dim > TRITON_MAX_HEAD_DIM:
        return f"the kernels take heads of at most {TRITON_MAX_HEAD_DIM} channels, got d = {head_dim}"
    if not _HAS_TRITON:
        return "triton is not installed"
    if _TRITON_VERSION is not None and _TRITON_VERSION < TRITON_MIN_VERSION:
        need, have = (".".join(map(str, v)) for v in (TRITON_MIN_VERSION, _TRITON_VERSION))
        return f"the kernels need triton >= {need} (plan_costs.TRITON_MIN_VERSION), this is triton {have}"
    return None


def resolve_backend(backend: Optional[str], device_type: str, dtype: torch.dtype, head_dim: int) -> str:
    """The backend that serves a call: ``backend`` (or ``$MSSF_SAMPLING_BACKEND``) when given and not
    ``"auto"``, else the device's entry of ``SAMPLING_BACKENDS`` (``"triton"`` only where it can serve).

    Raises:
        MSSFError: for an unknown backend, or ``"triton"`` forced where it cannot serve (e.g. CPU
            tensors without the interpreter, float64, no triton or one older than ``TRITON_MIN_VERSION``).
    """
    source = "backend"
    if backend is None or backend == "auto":
        env = os.environ.get(ENV_VAR, "")
        if env and env != "auto":
            backend, source = env, f"${ENV_VAR}"
    if backend is None or backend == "auto":
        choice = SAMPLING_BACKENDS.get(device_type, SAMPLING_FALLBACK)
        if choice == "triton" and (not _use_triton() or _triton_unusable(device_type, dtype, head_dim)):
            choice = SAMPLING_FALLBACK
        return choice
    if backend not in BACKENDS:
        raise MSSFError(f"{source}: expected 'auto' or one of {BACKENDS}, got {backend!r}")
    if backend == "triton":
        why = _triton_unusable(device_type, dtype, head_dim)
        if why:
            raise MSSFError(f"{source}: 'triton' cannot serve these inputs: {why}")
    return backend


# ---------------------------------------------------------------------------------------------------
# backends (levels (I, 1, C, H_l, W_l), projection (M, d, C) and (M, d))
# ---------------------------------------------------------------------------------------------------
def _touched_skipping(*args) -> Tensor:
    """The CPU plans, the queries that read no pixel left out first: inside the registered op, which
    serves graph capture, i.e. MSDFF's static layout, whose invalid (voxel, camera) pairs sit at
    ``uv = -1`` (at 25 % invalid pairs, 130 -> 75 ms for a training step's sampling)."""
    return touched.sample_project(*args, skip_unread=True)


_AUTOGRAD_BACKENDS = {"grid": grid.sample_project, "touched": touched.sample_project}  # (called directly)
_OP_BACKENDS = {"grid": grid.sample_project, "touched": _touched_skipping}  # (inside the registered ops)


def _triton_failed(exc: BaseException) -> None:
    if not _TRITON_FAILURE:
        _TRITON_FAILURE.append(f"{type(exc).__name__}: {exc}")
        warnings.warn(f"mssf_blocks: the Triton sampling kernels failed ({_TRITON_FAILURE[0]}); the grid path "
                      "(F.grid_sample) serves from now on", RuntimeWarning, stacklevel=3)


def _interpreting() -> bool:
    return os.environ.get("TRITON_INTERPRET") == "1"


def _use_triton() -> bool:
    """Triton, unless it failed before (under the interpreter, i.e. checking the kernels, failures raise)."""
    return not _TRITON_FAILURE or _interpreting()


def _forward_impl(levels, image_index, locations, weights, proj_weight, proj_bias, backend) -> Tensor:
    if backend == "triton" and _use_triton():
        from mssf_blocks.functional.deform.triton import launch as triton_backend
        try:
            return triton_backend.forward([v[:, 0] for v in levels], image_index, locations, weights,
                                          proj_weight, proj_bias)
        except Exception as exc:  # noqa: BLE001 - any compile / launch failure: warn once, grid path
            if _interpreting():
                raise
            _triton_failed(exc)
    fn = _OP_BACKENDS.get(backend, grid.sample_project)
    return fn(levels, image_index, locations, weights, proj_weight, proj_bias)


def _autograd_on() -> contextlib.ExitStack:
    """Autograd inside a custom op's implementation, which the dispatcher runs below autograd
    (``_AutoDispatchBelowAutograd``): the autograd dispatch keys are taken off the excluded set for
    the block (private API, guarded; ``torch.enable_grad()`` alone records nothing there)."""
    stack = contextlib.ExitStack()
    guard = getattr(torch._C, "_SetExcludeDispatchKeyGuard", None)
    keys = getattr(torch._C, "DispatchKey", None)
    if guard is not None and keys is not None:
        for name in ("AutogradFunctionality", "AutogradOther", "ADInplaceOrView"):
            if hasattr(keys, name):
                stack.enter_context(guard(getattr(keys, name), False))
    stack.enter_context(torch.enable_grad())
    return stack


def _grad_flags(levels, proj_weight, proj_bias) -> Tuple[bool, bool]:
    """``(value_grad, levels_grad)``: whether the projection or the levels need gradients, and the levels."""
    levels_grad = any(t.requires_grad for t in levels)
    return levels_grad or proj_weight.requires_grad or proj_bias.requires_grad, levels_grad


def _grad_inputs(levels, locations, weights, proj_weight, proj_bias, value_grad, levels_grad):
    """Detached copies of the op's inputs, those that need gradients marked, and the list of those."""
    loc = locations.detach().requires_grad_()
    wt = weights.detach().requires_grad_()
    lv = [v.detach().requires_grad_(levels_grad) for v in levels]
    pw = proj_weight.detach().requires_grad_(value_grad)
    pb = proj_bias.detach().requires_grad_(value_grad)
    return (lv, loc, wt, pw, pb), [loc, wt] + (lv if levels_grad else []) + ([pw, pb] if value_grad else [])


def _forward_keep_impl(levels, image_index, locations, weights, proj_weight, proj_bias, backend, value_grad,
                       levels_grad):
    """The forward of an autograd backend run under autograd, its graph kept for the backward (``kept.py``)."""
    levels_grad = value_grad and levels_grad
    with _autograd_on():
        (lv, loc, wt, pw, pb), inputs = _grad_inputs(levels, locations, weights, proj_weight, proj_bias, value_grad,
                                                     levels_grad)
        out = _OP_BACKENDS[backend](lv, image_index, loc, wt, pw, pb)
    return out.detach(), kept.keep(out, inputs, (backend, value_grad, levels_grad))


def _backward_impl(grad, levels, image_index, locations, weights, proj_weight, proj_bias, backend, value_grad,
                   levels_grad=True, graph_key=None):
    """``(grad levels or [], grad locations, grad weights, grad proj_weight, grad proj_bias)``: ``value_grad``
    whether the projection or the levels need gradients, ``levels_grad`` whether the levels do (the
    recomputed forward then leaves out the dense level gradient, e.g. of a frozen image branch);
    ``graph_key``: the key of the graph the forward kept (``kept.py``), if it did."""
    levels_grad = value_grad and levels_grad
    if backend == "triton" and _use_triton():
        from mssf_blocks.functional.deform.triton import launch as triton_backend
        try:
            gl, gloc, gwt, gw, gb = triton_backend.backward(
                grad, [v[:, 0] for v in levels], image_index, locations, weights, proj_weight, proj_bias,
                value_grad)
            if gl is None:
                return [], gloc, gwt, torch.zeros_like(proj_weight), torch.zeros_like(proj_bias)
            return [g.view(v.shape) for g, v in zip(gl, levels)] if levels_grad else [], gloc, gwt, gw, gb
        except Exception as exc:  # noqa: BLE001
            if _interpreting():
                raise
            _triton_failed(exc)
    fn = _OP_BACKENDS.get(backend, grid.sample_project)
    graph = None if graph_key is None else kept.take(graph_key, (backend, value_grad, levels_grad))
    with _autograd_on():
        if graph is None:  # (no graph kept: the forward again, under autograd)
            (lv, loc, wt, pw, pb), inputs = _grad_inputs(levels, locations, weights, proj_weight, proj_bias,
                                                         value_grad, levels_grad)
            graph = fn(lv, image_index, loc, wt, pw, pb), inputs
        out, inputs = graph
        grads = torch.autograd.grad(out, inputs, grad, allow_unused=True)
    grads = [torch.zeros_like(t) if g is None else g for g, t in zip(grads, inputs)]
    if not value_grad:
        return [], grads[0], grads[1], torch.zeros_like(proj_weight), torch.zeros_like(proj_bias)
    return grads[2:-2] if levels_grad else [], grads[0], grads[1], grads[-2], grads[-1]


def _unaliased(t: Tensor, taken: set) -> Tensor:
    """``t``, or a copy where its memory is an input's or an earlier output's (a custom op's outputs may
    alias neither); ``taken`` collects the storages handed out."""
    ptr = t.untyped_storage().data_ptr()
    if ptr in taken or not t.numel():  # (empty tensors: no address to tell them apart)
        t = t.clone()
        ptr = t.untyped_storage().data_ptr()
    taken.add(ptr)
    return t


# ---------------------------------------------------------------------------------------------------
# registration
# ---------------------------------------------------------------------------------------------------
_OP = _OP_KEEP = None
if torch_versions.has("custom_op"):  # torch >= 2.4; older: the entry calls the backends itself

    @torch.library.custom_op("mssf_blocks::deform_sample_project", mutates_args=())
    def _op(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor, proj_weight: Tensor,
            proj_bias: Tensor, backend: str) -> Tensor:
        return _forward_impl(levels, image_index, locations, weights, proj_weight, proj_bias, backend)

    @torch.library.custom_op("mssf_blocks::deform_sample_project_keep", mutates_args=())
    def _op_keep(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor, proj_weight: Tensor,
                 proj_bias: Tensor, backend: str, value_grad: bool, levels_grad: bool) -> Tuple[Tensor, Tensor]:
        """The op's forward for the autograd backends that keeps its graph for the backward (``kept.py``):
        ``(out, key)``, the key a 0-d int64 tensor. Used under ``torch.compile`` with gradients."""
        return _forward_keep_impl(levels, image_index, locations, weights, proj_weight, proj_bias, backend,
                                  value_grad, levels_grad)

    @torch.library.custom_op("mssf_blocks::deform_sample_project_backward", mutates_args=())
    def _op_backward(grad: Tensor, levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                     proj_weight: Tensor, proj_bias: Tensor, backend: str, value_grad: bool,
                     levels_grad: bool = True, graph_key: Optional[Tensor] = None,
                     ) -> Tuple[List[Tensor], Tensor, Tensor, Tensor, Tensor]:
        gl, gloc, gwt, gw, gb = _backward_impl(grad.contiguous(), levels, image_index, locations, weights,
                                               proj_weight, proj_bias, backend, value_grad, levels_grad, graph_key)
        taken = {t.untyped_storage().data_ptr() for t in (grad, *levels, locations, weights, proj_weight, proj_bias)}
        return [_unaliased(g, taken) for g in gl], *(_unaliased(g, taken) for g in (gloc, gwt, gw, gb))

    def _fake_out(locations, levels, proj_weight):
        return locations.new_empty(locations.shape[0], proj_weight.shape[0], proj_weight.shape[1],
                                   dtype=levels[0].dtype)

    @_op.register_fake
    def _(levels, image_index, locations, weights, proj_weight, proj_bias, backend):
        return _fake_out(locations, levels, proj_weight)

    @_op_keep.register_fake
    def _(levels, image_index, locations, weights, proj_weight, proj_bias, backend, value_grad, levels_grad):
        # (the key lives on the CPU whatever the inputs' device: kept.keep makes it there, no device sync)
        return _fake_out(locations, levels, proj_weight), torch.empty((), dtype=torch.int64, device="cpu")

    @_op_backward.register_fake
    def _(grad, levels, image_index, locations, weights, proj_weight, proj_bias, backend, value_grad,
          levels_grad=True, graph_key=None):
        return ([torch.empty_like(v) for v in levels] if value_grad and levels_grad else [],
                torch.empty_like(locations),
                torch.empty_like(weights), torch.empty_like(proj_weight), torch.empty_like(proj_bias))

    def _save(ctx, inputs, graph_key=None):
        levels, image_index, locations, weights, proj_weight, proj_bias, backend = inputs[:7]
        ctx.backend, ctx.num_levels, ctx.extra_inputs = backend, len(levels), len(inputs) - 7
        ctx.value_grad, ctx.levels_grad = _grad_flags(levels, proj_weight, proj_bias)
        ctx.save_for_backward(*levels, image_index, locations, weights, proj_weight, proj_bias,
                              *([] if graph_key is None else [graph_key]))

    def _backward(ctx, grad, *_):
        saved = ctx.saved_tensors
        n = ctx.num_levels
        levels, (image_index, locations, weights, proj_weight, proj_bias) = list(saved[:n]), saved[n:n + 5]
        graph_key = saved[n + 5] if len(saved) > n + 5 else None
        gl, gloc, gwt, gw, gb = _op_backward(grad, levels, image_index, locations, weights, proj_weight, proj_bias,
                                             ctx.backend, ctx.value_grad, ctx.levels_grad, graph_key)
        rest = (None,) * (1 + ctx.extra_inputs)  # (backend and the keeping op's flags)
        if not ctx.value_grad:
            return ([None] * ctx.num_levels, None, gloc, gwt, None, None) + rest
        return (list(gl) if ctx.levels_grad else [None] * ctx.num_levels, None, gloc, gwt, gw, gb) + rest

    _op.register_autograd(_backward, setup_context=lambda ctx, inputs, output: _save(ctx, inputs))
    _op_keep.register_autograd(_backward, setup_context=lambda ctx, inputs, output: _save(ctx, inputs, output[1]))
    _OP, _OP_KEEP = _op, _op_keep


class _TritonFunction(torch.autograd.Function):  # (torch < 2.4 only: no custom_op)
    @staticmethod
    def forward(ctx, image_index, locations, weights, proj_weight, proj_bias, *levels):
        ctx.save_for_backward(image_index, locations, weights, proj_weight, proj_bias, *levels)
        return _forward_impl(list(levels), image_index, locations, weights, proj_weight, proj_bias, "triton")

    @staticmethod
    def backward(ctx, grad):
        image_index, locations, weights, proj_weight, proj_bias, *levels = ctx.saved_tensors
        value_grad = any(ctx.needs_input_grad[3:])
        gl, gloc, gwt, gw, gb = _backward_impl(grad.contiguous(), levels, image_index, locations, weights,
                                               proj_weight, proj_bias, "triton", value_grad)
        return (None, gloc, gwt) + ((gw, gb, *gl) if value_grad else (None,) * (2 + len(levels)))


# ---------------------------------------------------------------------------------------------------
# entry
# ---------------------------------------------------------------------------------------------------
def deform_sample_project(
    values: Sequence[Tensor],
    image_index: Tensor,
    locations: Tensor,
    weights: Tensor,
    proj_weight: Tensor,
    proj_bias: Optional[Tensor] = None,
    backend: Optional[str] = "auto",
) -> Tensor:
    """Multi-scale deformable sampling of per-head projected values, by the backend of the device.

    Args:
        values: ``L`` raw levels ``(I, 1, C, H_l, W_l)`` (one map shared by the heads; the projection
            is part of the op), same ``I``, ``C``, dtype and device.
        image_index: ``(Q,)`` integer image of every query, in ``[0, I)``.
        locations: ``(Q, M, L, P, 2)`` normalised ``(u, v)`` (any strides).
        weights: ``(Q, M, L, P)`` attention weights.
        proj_weight: ``(M, d, C)`` per-head projection; ``proj_bias``: ``(M, d)`` or ``None``.
        backend: ``"auto"`` (the device's entry of ``plan_costs.SAMPLING_BACKENDS``, or
            ``$MSSF_SAMPLING_BACKEND`` when set), ``"touched"``, ``"grid"`` or ``"triton"``.

    Returns:
        ``(Q, M, d)``, differentiable w.r.t. every floating input.

    Raises:
        MSSFError: on bad shapes / dtypes / indices (naming the argument), an unknown backend, or
            ``"triton"`` forced where it cannot serve (CPU tensors without ``TRITON_INTERPRET=1``,
            float64, heads wider than ``TRITON_MAX_HEAD_DIM``, no triton or one older than
            ``plan_costs.TRITON_MIN_VERSION``).

    Example:
        >>> val = [torch.ones(1, 1, 2, 2, 2)]  # I = 1, C = 2, a 2x2 map of ones
        >>> loc = torch.tensor([0.0, 0.0]).view(1, 1, 1, 1, 2)  # image corner: 1/4 of the mass inside
        >>> w, b = torch.ones(1, 1, 2), torch.full((1, 1), 10.0)
        >>> deform_sample_project(val, torch.tensor([0]), loc, torch.ones(1, 1, 1, 1), w, b).item()
        3.0
    """
    levels, dims = _check_deform_inputs(values, image_index, locations, weights)
    if dims["Mv"] != 1:
        raise MSSFError(f"values: expected raw levels (I, 1, C, H_l, W_l) shared by the heads, got Mv = {dims['Mv']}")
    check_projection(proj_weight, proj_bias, levels, dims)
    return sample_project_unchecked(levels, image_index, locations, weights, proj_weight, proj_bias, backend)


def sample_project_unchecked(levels: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor,
                             proj_weight: Tensor, proj_bias: Optional[Tensor], backend: Optional[str]) -> Tensor:
    """:func:`deform_sample_project` without the input checks (no host synchronisation), for callers that
    built the inputs themselves (MSDFF)."""
    if proj_bias is None:
        proj_bias = proj_weight.new_zeros(proj_weight.shape[:2])
    choice = resolve_backend(backend, locations.device.type, levels[0].dtype, proj_weight.shape[1])
    args = (list(levels), image_index, locations, weights, proj_weight, proj_bias)
    if choice in _AUTOGRAD_BACKENDS and not is_tracing():
        return _AUTOGRAD_BACKENDS[choice](*args)  # native autograd: no second forward in backward (module doc)
    if _OP is not None:
        if choice in _AUTOGRAD_BACKENDS and torch_versions.is_compiling() and not torch_versions.is_exporting():
            value_grad, levels_grad = _grad_flags(levels, proj_weight, proj_bias)
            if torch.is_grad_enabled() and (value_grad or locations.requires_grad or weights.requires_grad):
                return _OP_KEEP(*args, choice, value_grad, levels_grad)[0]  # (no second forward: kept.py)
        return _OP(*args, choice)
    if choice == "triton":
        return _TritonFunction.apply(image_index, locations, weights, proj_weight, proj_bias, *levels)
    return _AUTOGRAD_BACKENDS[choice](*args)
