"""mmengine 0.10 checkpoints loaded with torch's weights-only unpickler: the allow-list of what they hold.

A checkpoint written by mmengine's ``CheckpointHook`` (``Runner.save_checkpoint``) holds, besides tensors and
plain Python values: the message hub's ``HistoryBuffer`` s (numpy arrays of the logged scalars, and their
statistics methods, pickled as ``getattr(HistoryBuffer, 'mean')`` ...) and numpy scalars
(``runtime_info['eta']``), and the parameter schedulers' state, in which ``OneCycleParamScheduler`` keeps its
annealing function (``getattr(OneCycleParamScheduler, '_annealing_cos')``). Measured on checkpoints of the
shipped configs (``torch.serialization.get_unsafe_globals_in_checkpoint``, then the pickle's ``getattr``
calls): exactly ``HistoryBuffer``, ``numpy.ndarray``, ``numpy.dtype``, numpy's ``scalar`` and
``_reconstruct``, ``OneCycleParamScheduler`` and ``builtins.getattr``. ``getattr`` is not allow-listed as such
(it would reach any attribute of any allowed object): a stand-in registered under its name gives only those
methods of those two classes.

:func:`weights_only_checkpoints` makes mmengine's local checkpoint loader (``load_from``, ``--resume``,
``init_cfg=dict(type="Pretrained")``) call ``torch.load(weights_only=True)`` with that allow-list, whatever
torch's default, and turns a refusal into an :class:`~mssf_blocks.errors.MSSFError` naming the file. torch
< 2.6 cannot register the ``getattr`` stand-in (its allow-list takes objects, not names): there the loader
unpickles in full, as torch's default did before 2.6, and says so.
"""

from __future__ import annotations

import os
import pickle
import sys
from contextlib import contextmanager
from typing import Any, Iterator, List

import torch

from mssf_blocks import _compat
from mssf_blocks.errors import MSSFError

__all__ = ["checkpoint_globals", "weights_only_checkpoints", "load_from_local_weights_only"]

def _methods() -> dict:
    """class -> the method names mmengine keeps in a checkpoint: the annealing functions of
    ``OneCycleParamScheduler.__init__`` and ``HistoryBuffer``'s statistics (``_statistics_methods``)."""
    from mmengine.logging.history_buffer import HistoryBuffer
    from mmengine.optim.scheduler.param_scheduler import OneCycleParamScheduler

    stats = {n for n, f in HistoryBuffer._statistics_methods.items() if getattr(HistoryBuffer, n, None) is f}
    return {OneCycleParamScheduler: {"_annealing_cos", "_annealing_linear"},
            HistoryBuffer: stats | {"min", "max", "current", "mean"}}


def _checkpoint_method(owner: Any, name: str) -> Any:
    """Registered as ``builtins.getattr``: only those methods (:func:`_methods`), nothing else."""
    if isinstance(owner, type) and name in _methods().get(owner, ()):
        return getattr(owner, name)
    raise pickle.UnpicklingError(f"getattr({owner!r}, {name!r}): not a method mmengine keeps in its checkpoints")


def checkpoint_globals() -> List[Any]:
    """What mmengine 0.10's checkpoints need beyond torch's weights-only defaults (module doc)."""
    import numpy as np

    try:
        from numpy._core.multiarray import _reconstruct, scalar
    except ImportError:  # numpy < 2
        from numpy.core.multiarray import _reconstruct, scalar
    dtypes = [type(np.dtype(k)) for k in (np.float64, np.float32, np.int64, np.int32, np.bool_)]
    return [np.ndarray, np.dtype, scalar, _reconstruct, *dtypes, *_methods(), (_checkpoint_method, "builtins.getattr")]


def _refusal(filename: str, exc: Exception) -> MSSFError:
    lines = [ln.strip() for ln in str(exc).splitlines() if "WeightsUnpickler error" in ln or "Unsupported" in ln]
    detail = lines[0] if lines else str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return MSSFError(
        f"checkpoint: {filename} holds objects that are neither tensors nor what mmengine 0.10's checkpoints hold "
        f"({detail}); refused: unpickling them could run code from the file. Load checkpoints written by "
        "mmengine's Runner (this model's training), or extract their weights yourself from a file you trust")


def load_from_local_weights_only(filename: str, map_location: Any = None) -> Any:
    """``torch.load(filename, weights_only=True)`` with :func:`checkpoint_globals` allowed (torch >= 2.6);
    a refused file raises :class:`MSSFError`. Before torch 2.6: a full load, with a note on stderr."""
    filename = os.path.expanduser(filename)
    if not os.path.isfile(filename):
        raise FileNotFoundError(f"{filename} can not be found.")
    if _compat.TORCH_VERSION < (2, 6):
        print(f"mssf_examples.mmdet3d: torch {torch.__version__} cannot allow-list mmengine's checkpoint objects "
              f"by name (torch >= 2.6 can); unpickling {filename} in full: load only checkpoints you trust",
              file=sys.stderr)
        return torch.load(filename, map_location=map_location, weights_only=False)
    with torch.serialization.safe_globals(checkpoint_globals()):
        try:
            return torch.load(filename, map_location=map_location, weights_only=True)
        except pickle.UnpicklingError as exc:
            raise _refusal(filename, exc) from None


@contextmanager
def weights_only_checkpoints() -> Iterator[None]:
    """Within: mmengine's local checkpoint loader is :func:`load_from_local_weights_only` (restored after)."""
    from mmengine.runner.checkpoint import CheckpointLoader

    schemes = CheckpointLoader._schemes
    previous = schemes.get("")
    schemes[""] = load_from_local_weights_only  # same key, same place in the ordered lookup (the catch-all, last)
    try:
        yield
    finally:
        if previous is None:
            del schemes[""]
        else:
            schemes[""] = previous
