"""Autograd graphs that the sampling op's forward keeps for its backward (the CPU backends, compiled).

A custom op's implementation runs below autograd, so its backward cannot reuse what the forward
computed: it would run the backend's forward a second time, under autograd, before differentiating
it (a training step of ``FusionBlock(MSDFF)`` compiled on one core: 15 ms of 130). Under
``torch.compile`` with gradients, MSDFF's sampling therefore goes through
``torch.ops.mssf_blocks.deform_sample_project_keep`` (``op.py``): its forward runs the backend under
autograd, keeps the graph here under a fresh integer key and returns the key as a second output (a
0-d int64 tensor that the compiled graph saves for the backward like any activation); the backward
takes the graph by its key and differentiates it, as eager autograd would.

Keys are never reused, so a graph is only ever found by the call that made it. A graph leaves when
its backward takes it, when the key tensor is freed (the forward's graph was dropped without a
backward) or when more than :data:`MAX_KEPT` graphs wait (the oldest first); a backward that finds no
graph recomputes the forward, with the same numbers.
"""

from __future__ import annotations

import itertools
import threading
import weakref
from collections import OrderedDict
from typing import Hashable, List, Optional, Tuple

import torch
from torch import Tensor

__all__ = ["keep", "take", "waiting", "MAX_KEPT"]

#: Graphs kept at most (forward calls awaiting their backward: a few per model and step).
MAX_KEPT = 64
_GRAPHS: "OrderedDict[int, Tuple[Tensor, List[Tensor], Hashable]]" = OrderedDict()
_KEYS = itertools.count(1)
_LOCK = threading.Lock()


def _drop(key: int) -> None:
    with _LOCK:
        _GRAPHS.pop(key, None)


def keep(out: Tensor, inputs: List[Tensor], tag: Hashable) -> Tensor:
    """Keep ``out``'s autograd graph w.r.t. ``inputs``, made as ``tag`` says (backend, which inputs);
    returns its key, a 0-d int64 tensor."""
    key = next(_KEYS)
    with _LOCK:
        _GRAPHS[key] = (out, inputs, tag)
        while len(_GRAPHS) > MAX_KEPT:
            _GRAPHS.popitem(last=False)
    handle = torch.tensor(key, dtype=torch.int64)
    weakref.finalize(handle, _drop, key)
    return handle


def take(key: Tensor, tag: Hashable) -> Optional[Tuple[Tensor, List[Tensor]]]:
    """``(out, inputs)`` of the graph kept under ``key`` (removed), or ``None`` (also when it was made
    for another ``tag``)."""
    with _LOCK:
        graph = _GRAPHS.pop(int(key), None)
    return graph[:2] if graph is not None and graph[2] == tag else None


def waiting() -> int:
    """How many graphs wait for their backward (for tests)."""
    with _LOCK:
        return len(_GRAPHS)
