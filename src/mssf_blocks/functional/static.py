"""Static-shape formulations of the blocks' data-dependent steps (the compile / export path).

Every function here has outputs and intermediates whose sizes depend on the input *sizes* only, never
on the input values: no ``nonzero``, ``unique``, boolean-mask indexing or ``.item()``. That is what
``torch.compile(dynamic=True)`` needs to keep one graph for every voxel count, and what ``torch.export``
/ ONNX need to export at all. The results equal the eager paths' (same formulas; tests compare them):

* :func:`grid_sample_static` - multi-scale deformable sampling with ``F.grid_sample``: the sampling
  op's grid path, which lives with the other backends (``functional/deform/grid.py``; re-exported here).
* :func:`linear_norm_visible_static` - ``Linear + norm`` on the rows seen by a camera, exact zeros
  elsewhere; a training-mode BatchNorm takes its statistics over the visible rows only (masked sums).
* :func:`segment_slots` - the sort join of :func:`~mssf_blocks.functional.geometry.voxel_centroids`
  with one slot per key *occurrence* (``N + P`` slots) instead of per distinct key.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .deform.grid import grid_sample_static

__all__ = ["grid_sample_static", "linear_norm_visible_static", "segment_slots"]


def _masked_batch_norm(norm: nn.modules.batchnorm._BatchNorm, y: Tensor, visible: Tensor) -> Tensor:
    """``norm(y[visible])`` of a training-mode BatchNorm, computed on all rows with masked statistics.

    The arithmetic of ``F.batch_norm`` in training mode (biased variance for the normalisation,
    unbiased for the running variance, ``momentum=None`` as a cumulative average); running statistics
    are updated only when at least two rows are visible (the eager path then raises or skips).
    """
    mask = visible.to(y.dtype).view(-1, 1)
    count = mask.sum()
    denom = count.clamp(min=1.0)
    mean = (y * mask).sum(0) / denom
    centred = y - mean
    var = (centred * centred * mask).sum(0) / denom
    out = centred * torch.rsqrt(var + norm.eps)
    if norm.affine:
        out = out * norm.weight + norm.bias
    if norm.training and norm.track_running_stats:
        with torch.no_grad():
            enough = count > 1
            norm.num_batches_tracked.add_(enough.to(norm.num_batches_tracked.dtype))
            if norm.momentum is None:
                factor = 1.0 / norm.num_batches_tracked.clamp(min=1).to(y.dtype)
            else:
                factor = torch.full((), norm.momentum, dtype=y.dtype, device=y.device)
            factor = torch.where(enough, factor, torch.zeros_like(factor))
            unbiased = var * count / (count - 1.0).clamp(min=1.0)
            norm.running_mean.copy_(norm.running_mean + factor.to(norm.running_mean.dtype)
                                    * (mean.detach().to(norm.running_mean.dtype) - norm.running_mean))
            norm.running_var.copy_(norm.running_var + factor.to(norm.running_var.dtype)
                                   * (unbiased.detach().to(norm.running_var.dtype) - norm.running_var))
    return out


def linear_norm_visible_static(linear: nn.Module, norm: nn.Module, x: Tensor, visible: Tensor) -> Tensor:
    """``norm(linear(x))`` on the visible rows, exact zeros elsewhere; static shapes.

    A row-wise norm (any norm in eval mode, LayerNorm, Identity) runs on every row and the invisible
    rows are zeroed; a BatchNorm that uses batch statistics takes them over the visible rows only, as
    the eager path (which gathers those rows) does.
    """
    y = linear(x)
    batch_stats = isinstance(norm, nn.modules.batchnorm._BatchNorm) and (
        norm.training or not norm.track_running_stats
    )
    if batch_stats and not isinstance(norm, nn.SyncBatchNorm) and y.dim() == 2:
        y = _masked_batch_norm(norm, y, visible)
    else:
        y = norm(y)
    return torch.where(visible.view(-1, 1), y, y.new_zeros(()))


def segment_slots(keys: Tensor) -> Tensor:
    """``(K,)`` slot of every key: equal keys share a slot, slots in ``[0, K)`` (static size ``K``).

    The static-shape counterpart of ``torch.unique(keys, return_inverse=True)[1]``: a sort, a cumulative
    count of the key changes, and the inverse permutation (slots are ordered like the keys, but unused
    slots may remain at the end). The sort need not be stable (equal keys share a slot whatever their
    order), and ONNX has no stable sort (``TopK``).
    """
    sorted_keys, order = torch.sort(keys)
    change = torch.cat([torch.ones_like(sorted_keys[:1], dtype=torch.bool), sorted_keys[1:] != sorted_keys[:-1]])
    seg = torch.cumsum(change.to(torch.int64), 0) - 1
    return torch.empty_like(seg).scatter_(0, order, seg)
