"""MSDFF's attention queries: which (voxel, camera) pairs are sampled, and the reduction over cameras.

One attention query per (voxel, camera) pair where the voxel is valid. Offsets and attention weights
depend on the voxel's query only, so they are computed per voxel and gathered. Four layouts:

* ``"all"`` (static shapes: graph capture, the grid plan, the sampling op on a GPU): a query for every
  pair, invalid ones at ``uv = -1`` (finite; masked out by :func:`camera_mean`, no gradient), no gather
  and no host synchronisation;
* ``"each"``: one camera that sees every voxel, no gathers or scatters;
* ``"seen"``: one camera that misses some voxels (the usual case: the radar sees wider than the
  camera): the seen voxels' queries only, the output projection on those rows, scattered once at the end;
* ``"gathered"``: several cameras, the valid pairs gathered (``nonzero``) and scattered back.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.functional.sampling import camera_mean

__all__ = ["Pairs", "select_pairs", "reduce_cameras"]

LocationsAndWeights = Callable[[Tensor, Tensor, Sequence[Tuple[int, int]]], Tuple[Tensor, Tensor]]


class Pairs(NamedTuple):
    locations: Tensor  # (Q, M, L, P, 2)
    weights: Tensor  # (Q, M, L, P)
    image_index: Tensor  # (Q,) in [0, B * V)
    layout: str  # "all", "each", "seen" or "gathered"
    seen: Optional[Tensor] = None  # "seen": the rows of the seen voxels
    n_idx: Optional[Tensor] = None  # "gathered": voxel and camera of every query
    v_idx: Optional[Tensor] = None


def select_pairs(locations_and_weights: LocationsAndWeights, query: Tensor, uv: Tensor, valid: Tensor,
                 batch_index: Tensor, sizes: Sequence[Tuple[int, int]], static: bool) -> Pairs:
    """The queries of ``query (N, E)`` at ``uv (N, V, 2)`` where ``valid (N, V)``, in the layout above."""
    n, v = valid.shape
    if static:
        uv = torch.where(valid[..., None], uv, uv.new_full((), -1.0))
        if v == 1:
            locations, weights = locations_and_weights(query, uv[:, 0], sizes)
        else:
            locations, weights = locations_and_weights(query, uv.new_zeros(n, 2), sizes)
            locations = (locations[:, None] + uv[:, :, None, None, None, :]).flatten(0, 1)
            weights = weights[:, None].expand((n, v) + weights.shape[1:]).flatten(0, 1)
        image_index = (batch_index[:, None] * v + torch.arange(v, device=uv.device)).reshape(-1)
        return Pairs(locations, weights, image_index, "all")
    if v == 1 and bool(valid.all()):
        locations, weights = locations_and_weights(query, uv[:, 0], sizes)
        return Pairs(locations, weights, batch_index, "each")
    if v == 1:
        seen = valid[:, 0].nonzero().squeeze(1)  # (the rows of the seen voxels)
        locations, weights = locations_and_weights(query[seen], uv[seen, 0], sizes)
        return Pairs(locations, weights, batch_index[seen], "seen", seen=seen)
    n_idx, v_idx = valid.nonzero(as_tuple=True)
    locations, weights = locations_and_weights(query, uv.new_zeros(n, 2), sizes)
    locations = locations[n_idx] + uv[n_idx, v_idx][:, None, None, None, :]
    return Pairs(locations, weights[n_idx], batch_index[n_idx] * v + v_idx, "gathered", n_idx=n_idx, v_idx=v_idx)


def reduce_cameras(heads: Tensor, pairs: Pairs, valid: Tensor) -> Tensor:
    """``(rows, E)``: per voxel the mean over its valid cameras of the queries' ``heads (Q, M, d)``
    (``"seen"``: the seen voxels' rows only)."""
    n, v = valid.shape
    e = heads.shape[1] * heads.shape[2]
    if pairs.layout in ("each", "seen"):
        return heads.reshape(-1, e)
    if pairs.layout == "all":
        return camera_mean(heads.reshape(n, v, e), valid)
    per_camera = heads.new_zeros(n, v, e).index_put((pairs.n_idx, pairs.v_idx), heads.reshape(-1, e))
    return camera_mean(per_camera, valid)
