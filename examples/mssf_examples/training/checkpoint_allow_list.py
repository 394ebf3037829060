"""Checkpoints unpickled with an allow-list of globals on every torch, for the framework entries
(``python -m mssf_examples.mmdet3d``, ``python -m mssf_examples.openpcdet``).

torch >= 2.6 loads with ``weights_only=True`` by default and takes extra globals by object or by name
(``torch.serialization.safe_globals``). Before 2.6 (the torch of mmcv 2.1's wheels, 2.1, and of many
OpenPCDet set-ups) ``torch.load`` unpickles in full unless told otherwise, so a crafted checkpoint runs code.
There, :func:`allow_list_pickle_module` gives ``torch.load`` an unpickler whose globals come from a list
only: torch's own weights-only globals (tensors, storages, ``OrderedDict``), ``_codecs.encode`` (protocol
2's bytes: a numpy array's data) and the entry's extra ones. A global outside it is refused before it is
imported (the standard library's "restricting globals" recipe: every way a pickle runs code goes through a
global), and the refusal is an :class:`~mssf_blocks.errors.MSSFError` naming the file.
"""

from __future__ import annotations

import _codecs
import _compat_pickle
import functools
import pickle
from contextlib import contextmanager
from types import SimpleNamespace
from typing import Any, Callable, Dict, Iterator, Sequence

import torch

from mssf_blocks.errors import MSSFError

__all__ = ["allowed_by_name", "allow_list_pickle_module", "refusal", "restricted_torch_load"]


def allowed_by_name(extra: Sequence[Any]) -> Dict[str, Any]:
    """``"module.name"`` -> object: torch's weights-only globals, ``_codecs.encode`` and ``extra`` (objects,
    or ``(object, "module.name")`` pairs; numpy's ``multiarray`` under both of its module names, ``numpy.core``
    before numpy 2 and ``numpy._core`` after)."""
    from torch import _weights_only_unpickler

    allowed: Dict[str, Any] = dict(_weights_only_unpickler._get_allowed_globals())
    allowed["_codecs.encode"] = _codecs.encode  # torch >= 2.3 lists it too
    for g in extra:
        obj, name = g if isinstance(g, tuple) else (g, f"{g.__module__}.{g.__qualname__}")
        allowed[name] = obj
        if ".multiarray." in name:
            for core in ("numpy.core.", "numpy._core."):
                allowed[core + name.split("core.", 1)[1]] = obj
    return allowed


class AllowListUnpickler(pickle.Unpickler):
    """A pickle ``Unpickler`` whose globals come from :attr:`allowed` only."""

    allowed: Dict[str, Any] = {}

    def find_class(self, module: str, name: str) -> Any:
        # protocol 2 (torch.save's) names Python 2's modules (``__builtin__.getattr``): map them as pickle does
        module, name = _compat_pickle.NAME_MAPPING.get((module, name), (module, name))
        module = _compat_pickle.IMPORT_MAPPING.get(module, module)
        key = f"{module}.{name}"
        if key not in self.allowed:
            raise pickle.UnpicklingError(f"WeightsUnpickler error: Unsupported global: GLOBAL {key} was not an "
                                         "allowed global")
        return self.allowed[key]


def allow_list_pickle_module(extra: Sequence[Any]) -> Any:
    """A ``pickle_module`` for ``torch.load`` whose ``Unpickler`` takes :func:`allowed_by_name` (``extra``)
    only (torch subclasses it and resolves storages itself before asking it)."""
    unpickler = type("Unpickler", (AllowListUnpickler,), {"allowed": allowed_by_name(extra)})
    return SimpleNamespace(__name__="mssf_allow_list_pickle", Unpickler=unpickler,
                           load=lambda f, **kw: unpickler(f, **kw).load())


def refusal(filename: Any, exc: Exception, holds: str, instead: str) -> MSSFError:
    """The error for a refused checkpoint: the file, the refused global, what is allowed and what to do."""
    lines = [ln.strip() for ln in str(exc).splitlines() if "WeightsUnpickler error" in ln or "Unsupported" in ln]
    detail = lines[0] if lines else str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return MSSFError(f"checkpoint: {filename} holds objects that are neither tensors nor {holds} ({detail}); "
                     f"refused: unpickling them could run code from the file. {instead}")


@contextmanager
def restricted_torch_load(extra: Sequence[Any], holds: str, instead: str) -> Iterator[None]:
    """Within (torch < 2.6 only; later torch refuses by itself): every ``torch.load`` that asks neither for
    ``weights_only`` nor for its own ``pickle_module`` (a framework's ``torch.load(filename, map_location)``)
    unpickles through :func:`allow_list_pickle_module` (``extra``); a refusal raises :func:`refusal`."""
    from mssf_blocks import torch_versions as _compat

    if _compat.TORCH_VERSION >= (2, 6):
        yield
        return
    original: Callable = torch.load
    module = allow_list_pickle_module(extra)

    @functools.wraps(original)
    def load(f, map_location=None, pickle_module=None, *args, weights_only=None, **kwargs):
        if pickle_module is not None or weights_only:
            return original(f, map_location, pickle_module, *args, weights_only=bool(weights_only), **kwargs)
        try:
            return original(f, map_location, module, *args, weights_only=False, **kwargs)
        except pickle.UnpicklingError as exc:
            raise refusal(f, exc, holds, instead) from None

    torch.load = load
    try:
        yield
    finally:
        torch.load = original
