"""Every call that depends on the torch version, in one place, each with the version it serves.

The library runs on torch 2.1 (the torch of an mmdetection3d 1.4 / mmcv 2.1.0 environment) through the
newest release; CI runs the suite on the floor, the pinned and the newest torch (``docs/compatibility.md``).
Code elsewhere calls the functions below instead of the torch API that moved between versions.

Features a newer torch adds are detected (by the API, not by the version string, so a backport or a
nightly is judged by what it has). :func:`require` turns a missing one into an :class:`MSSFError` naming
the feature, the torch it needs and the torch installed; tests of these features skip with that message
(:func:`missing`). The versions in :data:`FEATURES` are the first torch release with the API, or for
graph capture of the blocks the oldest torch it is tested on (``_CAPTURE_VERIFIED``).
"""

from __future__ import annotations

import contextlib
import inspect
import re
from typing import Any, Callable, Dict, Optional, Tuple

import torch

from mssf_blocks.errors import MSSFError

__all__ = [
    "TORCH_VERSION", "FEATURES", "has", "missing", "require", "is_compiling", "is_exporting", "is_fake",
    "autocast_enabled", "grad_scaler", "register_pytree_node", "add_safe_globals",
]


def _parse(version: str) -> Tuple[int, int]:
    m = re.match(r"(\d+)\.(\d+)", version)
    return (int(m.group(1)), int(m.group(2))) if m else (0, 0)


#: ``(major, minor)`` of the installed torch
TORCH_VERSION: Tuple[int, int] = _parse(torch.__version__)


# ---------------------------------------------------------------------------------------------------
# detected features: name -> (first torch with it, what it is, detector)
# ---------------------------------------------------------------------------------------------------
def _has_pytree_keys() -> bool:
    from torch.utils import _pytree as pytree

    register = getattr(pytree, "register_pytree_node", None)
    return register is not None and "flatten_with_keys_fn" in inspect.signature(register).parameters


#: the oldest torch on which dynamo captures the blocks whole (torch.compile fullgraph, torch.export):
#: tested on 2.13 and the newest; torch 2.3.1 cannot trace their input checks (dict.setdefault on the named
#: sizes) nor build a FusionInputs in the graph, 2.1 neither; the releases in between are not tested
_CAPTURE_VERIFIED = (2, 13)


def _has_export_dynamic_shapes() -> bool:
    # torch.export.Dim (2.2), pytree key paths for the library's dataclasses (2.3), and a dynamo that
    # captures the blocks (see _CAPTURE_VERIFIED)
    export = getattr(torch, "export", None)
    return (export is not None and hasattr(export, "Dim") and _has_pytree_keys()
            and TORCH_VERSION >= _CAPTURE_VERIFIED)


def _has_onnx_dynamo() -> bool:
    onnx = getattr(torch, "onnx", None)
    return onnx is not None and "dynamo" in inspect.signature(onnx.export).parameters


def _has_custom_op() -> bool:
    library = getattr(torch, "library", None)
    return library is not None and hasattr(library, "custom_op") and hasattr(library, "register_fake")


def _has_fullgraph_capture() -> bool:
    # torch.compile(fullgraph=True, dynamic=True) of the blocks; on older torch it still runs them, with
    # graph breaks at the input checks (see _CAPTURE_VERIFIED)
    compiler = getattr(torch, "compiler", None)
    return compiler is not None and hasattr(compiler, "is_compiling") and TORCH_VERSION >= _CAPTURE_VERIFIED


_CPU_FLOAT16_AUTOCAST: Optional[bool] = None


def _has_cpu_float16_autocast() -> bool:
    global _CPU_FLOAT16_AUTOCAST
    if _CPU_FLOAT16_AUTOCAST is None:  # torch 2.1 warns, then raises on entering the context
        import warnings

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                with torch.autocast("cpu", dtype=torch.float16):
                    _CPU_FLOAT16_AUTOCAST = torch.mm(torch.ones(1, 1), torch.ones(1, 1)).dtype == torch.float16
        except RuntimeError:
            _CPU_FLOAT16_AUTOCAST = False
    return _CPU_FLOAT16_AUTOCAST


FEATURES: Dict[str, Tuple[str, str, Callable[[], bool]]] = {
    "export_dynamic_shapes": ("2.13", "torch.export with dynamic shapes (torch.export.Dim) of the library's "
                              "dataclasses (pytree key paths)", _has_export_dynamic_shapes),
    "onnx_dynamo": ("2.5", "torch.onnx.export(dynamo=True)", _has_onnx_dynamo),
    "custom_op": ("2.4", "torch.library.custom_op / register_fake (ops registered with torch)", _has_custom_op),
    "compile_dynamic": ("2.13", "torch.compile(fullgraph=True, dynamic=True) of the blocks (one graph for "
                        "every voxel count)", _has_fullgraph_capture),
    "cpu_float16_autocast": ("2.3", "float16 autocast on the CPU (older CPU autocast takes only bfloat16)",
                             _has_cpu_float16_autocast),
}


def has(feature: str) -> bool:
    """Whether the installed torch has ``feature`` (a key of :data:`FEATURES`)."""
    if feature not in FEATURES:
        raise MSSFError(f"feature: expected one of {sorted(FEATURES)}, got {feature!r}")
    return bool(FEATURES[feature][2]())


def missing(feature: str) -> Optional[str]:
    """``None`` when the installed torch has ``feature``, else why not (the message :func:`require` raises)."""
    if has(feature):
        return None
    version, what = FEATURES[feature][:2]
    return f"{what} needs torch >= {version}; this is torch {torch.__version__}"


def require(feature: str, caller: str = "") -> None:
    """Raise :class:`MSSFError` naming the torch version ``feature`` needs when the installed one lacks it."""
    reason = missing(feature)
    if reason is not None:
        raise MSSFError(f"{caller + ': ' if caller else ''}{reason}")


# ---------------------------------------------------------------------------------------------------
# shims: the same call on every torch from the floor up
# ---------------------------------------------------------------------------------------------------
def is_compiling() -> bool:
    """Whether dynamo is capturing a graph. ``torch.compiler.is_compiling`` from torch 2.3; before it,
    ``torch._utils.is_compiling`` (2.0 - 2.2), which dynamo constant-folds the same way."""
    compiler = getattr(torch, "compiler", None)
    if compiler is not None and hasattr(compiler, "is_compiling"):
        return bool(compiler.is_compiling())
    return bool(torch._utils.is_compiling())


def is_exporting() -> bool:
    """Whether ``torch.export`` is capturing (``torch.compiler.is_exporting``, torch 2.6; older exporters
    run under dynamo, so :func:`is_compiling` already says so there)."""
    compiler = getattr(torch, "compiler", None)
    return bool(compiler is not None and hasattr(compiler, "is_exporting") and compiler.is_exporting())


try:  # (private, hence guarded; in torch since 2.0) FakeTensors carry no data
    from torch._subclasses.fake_tensor import is_fake as _is_fake
except ImportError:  # pragma: no cover - depends on the torch version
    def _is_fake(x: Any) -> bool:
        return False


def is_fake(x: Any) -> bool:
    """Whether ``x`` is a FakeTensor (``torch._subclasses.fake_tensor.is_fake``, private: guarded)."""
    return bool(_is_fake(x))


def autocast_enabled(device_type: str) -> bool:
    """Whether ``torch.autocast`` is on for ``device_type``: ``torch.is_autocast_enabled(device_type)``
    from torch 2.4; before it, ``is_autocast_cpu_enabled()`` for the CPU and the argument-free
    ``is_autocast_enabled()`` (CUDA) for the rest."""
    try:
        return bool(torch.is_autocast_enabled(device_type))
    except TypeError:  # torch < 2.4: no device argument
        if device_type == "cpu":
            return bool(torch.is_autocast_cpu_enabled())
        return bool(torch.is_autocast_enabled())


def autocast_off(device_type: str):
    """A context that disables autocast for ``device_type`` when it is on (else does nothing)."""
    return torch.autocast(device_type, enabled=False) if autocast_enabled(device_type) else contextlib.nullcontext()


def grad_scaler(device_type: str, enabled: bool = True) -> Any:
    """A loss scaler for float16 training on ``device_type``: ``torch.amp.GradScaler(device_type)`` from
    torch 2.3; before it ``torch.cuda.amp.GradScaler`` (which is also the disabled no-op scaler elsewhere).
    An enabled scaler off CUDA on an older torch is refused (float16 CPU autocast needs torch 2.3 anyway)."""
    amp = getattr(torch, "amp", None)
    if amp is not None and hasattr(amp, "GradScaler"):
        return amp.GradScaler(device_type, enabled=enabled)
    if enabled and device_type != "cuda":
        raise MSSFError(f"grad_scaler: a float16 loss scaler on {device_type!r} needs torch >= 2.3 "
                        f"(torch.amp.GradScaler); this is torch {torch.__version__}")
    return torch.cuda.amp.GradScaler(enabled=enabled)


def add_safe_globals(objects: list) -> bool:
    """Allow-list ``objects`` for ``torch.load(weights_only=True)``: ``torch.serialization.add_safe_globals``
    from torch 2.4. Before it there is no allow-list and nothing to do: ``torch.load`` defaults to
    ``weights_only=False`` there (until 2.6), which loads them. Returns whether they were registered."""
    register = getattr(torch.serialization, "add_safe_globals", None)
    if register is None:
        return False
    register(list(objects))
    return True


def register_pytree_node(cls: type, flatten: Callable, unflatten: Callable, *, serialized_type_name: str,
                         flatten_with_keys: Callable, to_dumpable: Callable, from_dumpable: Callable) -> None:
    """Register ``cls`` with torch's pytree (no-op when it is registered). ``register_pytree_node`` with
    key paths from torch 2.3; 2.2 without ``flatten_with_keys_fn``; 2.1 the private ``_register_pytree_node``
    (no serialized name: torch.export of these inputs needs a newer torch, :data:`FEATURES`)."""
    from torch.utils import _pytree as pytree

    if cls in pytree.SUPPORTED_NODES:
        return
    kwargs: Dict[str, Any] = dict(to_dumpable_context=to_dumpable, from_dumpable_context=from_dumpable)
    register = getattr(pytree, "register_pytree_node", None)
    if register is None:  # torch 2.1
        pytree._register_pytree_node(cls, flatten, unflatten, **kwargs)
        return
    params = inspect.signature(register).parameters
    if "serialized_type_name" in params:
        kwargs["serialized_type_name"] = serialized_type_name
    if "flatten_with_keys_fn" in params:
        kwargs["flatten_with_keys_fn"] = flatten_with_keys
    register(cls, flatten, unflatten, **kwargs)


def mapping_key(name: str) -> Any:
    """``torch.utils._pytree.MappingKey(name)`` (torch 2.3, where key paths exist)."""
    from torch.utils import _pytree as pytree

    return pytree.MappingKey(name)



def _bag_weights_only_grad_ok() -> bool:
    """Whether ``embedding_bag`` accepts ``per_sample_weights`` that need a gradient with a table that
    does not (torch 2.1 fails an internal assert, ``isDifferentiableType``, in the forward)."""
    try:
        with torch.enable_grad():
            torch.nn.functional.embedding_bag(torch.zeros(1, 1, dtype=torch.long), torch.ones(1, 1),
                                              per_sample_weights=torch.ones(1, 1, requires_grad=True), mode="sum")
        return True
    except RuntimeError:
        return False


#: probed once at import (a constant to dynamo, so compiled graphs hold no probe)
_BAG_WEIGHTS_ONLY_GRAD: bool = _bag_weights_only_grad_ok()


def embedding_bag(input: Any, weight: Any, *args: Any, **kwargs: Any) -> Any:
    """``torch.nn.functional.embedding_bag``. Where torch (2.1) cannot differentiate the per-sample
    weights alone, the table is given a detached copy that needs a gradient (the same values and the
    same gradient for the weights; the table's gradient is computed and dropped)."""
    if not _BAG_WEIGHTS_ONLY_GRAD:
        psw = kwargs.get("per_sample_weights")
        if psw is not None and psw.requires_grad and not weight.requires_grad and torch.is_grad_enabled():
            weight = weight.detach().requires_grad_()
    return torch.nn.functional.embedding_bag(input, weight, *args, **kwargs)
