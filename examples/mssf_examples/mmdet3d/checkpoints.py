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
< 2.6 cannot register the ``getattr`` stand-in (its allow-list takes objects, not names; mmdetection3d 1.4's
mmcv 2.1 has wheels up to torch 2.1, so most of its users are there): there the same allow-list, plus the
globals of torch's own weights-only unpickler (tensors, storages, ``OrderedDict``), is enforced by a
restricted unpickler handed to ``torch.load`` as its ``pickle_module``
(:mod:`mssf_examples.training.checkpoint_allow_list`): a global outside it is refused before it is imported, so
nothing in the file can run code.
"""

from __future__ import annotations

import os
import pickle
from contextlib import contextmanager
from typing import Any, Iterator, List

import torch

from mssf_blocks import torch_versions as _compat

from ..training.checkpoint_allow_list import allow_list_pickle_module, refusal

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


_HOLDS = "what mmengine 0.10's checkpoints hold"
_INSTEAD = ("Load checkpoints written by mmengine's Runner (this model's training), or extract their weights "
            "yourself from a file you trust")


def load_from_local_weights_only(filename: str, map_location: Any = None) -> Any:
    """``torch.load(filename, weights_only=True)`` with :func:`checkpoint_globals` allowed (torch >= 2.6;
    before: the same allow-list through :func:`~mssf_examples.training.checkpoint_allow_list.allow_list_pickle_module`);
    a refused file raises
    :class:`MSSFError`."""
    filename = os.path.expanduser(filename)
    if not os.path.isfile(filename):
        raise FileNotFoundError(f"{filename} can not be found.")
    if _compat.TORCH_VERSION < (2, 6):
        try:
            return torch.load(filename, map_location=map_location,
                              pickle_module=allow_list_pickle_module(checkpoint_globals()), weights_only=False)
        except pickle.UnpicklingError as exc:
            raise refusal(filename, exc, _HOLDS, _INSTEAD) from None
    with torch.serialization.safe_globals(checkpoint_globals()):
        try:
            return torch.load(filename, map_location=map_location, weights_only=True)
        except pickle.UnpicklingError as exc:
            raise refusal(filename, exc, _HOLDS, _INSTEAD) from None


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
