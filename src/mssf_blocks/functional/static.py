"""Static-shape formulations of the blocks' data-dependent steps (the compile / export path).

Every function here has outputs and intermediates whose sizes depend on the input *sizes* only, never
on the input values: no ``nonzero``, ``unique``, boolean-mask indexing or ``.item()``. That is what
``torch.compile(dynamic=True)`` needs to keep one graph for every voxel count, and what ``torch.export``
/ ONNX need to export at all. The results equal the eager paths' (same formulas; tests compare them):

* :func:`grid_sample_static` - multi-scale deformable sampling with ``F.grid_sample`` (ONNX
  ``GridSample``, opset 16+): every query is sampled in every image of the batch and keeps its own
  image's result (a mask, no gather of per-image query lists). Cost and memory therefore grow with the
  number of images ``I = B * V``: the same as the eager ``grid_sample`` path for ``I = 1`` (a
  deployment batch of one frame and camera), ``I`` times it otherwise.
* :func:`linear_norm_visible_static` - ``Linear + norm`` on the rows seen by a camera, exact zeros
  elsewhere; a training-mode BatchNorm takes its statistics over the visible rows only (masked sums).
* :func:`segment_slots` - the sort join of :func:`~mssf_blocks.functional.geometry.voxel_centroids`
  with one slot per key *occurrence* (``N + P`` slots) instead of per distinct key.
"""

from __future__ import annotations

from typing import List, Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["grid_sample_static", "linear_norm_visible_static", "segment_slots"]


def _select_image(per_image: Tensor, image_index: Tensor) -> Tensor:
    """``per_image (I, Q, ...)`` -> ``(Q, ...)``: row ``q`` of image ``image_index[q]`` (a where-mask sum).

    ``torch.where`` (not a product with a one-hot mask) so that a non-finite sample of another image
    cannot leak in; its backward sends each query's gradient to its own image only.
    """
    num_images = per_image.shape[0]
    if num_images == 1:
        return per_image[0]
    mine = image_index.view(1, -1) == torch.arange(num_images, device=image_index.device).view(-1, 1)  # (I, Q)
    mine = mine.view(mine.shape + (1,) * (per_image.dim() - 2))
    return torch.where(mine, per_image, per_image.new_zeros(())).sum(0)


def grid_sample_static(
    values: List[Tensor], image_index: Tensor, locations: Tensor, weights: Tensor
) -> Tensor:
    """``F.grid_sample`` formulation of :func:`~mssf_blocks.functional.ms_deform_sample` with static shapes.

    Args:
        values: ``L`` levels ``(I, Mv, D, H_l, W_l)`` with ``Mv`` 1 (shared by all heads) or ``M``.
        image_index: ``(Q,)`` integer image of every query, in ``[0, I)``.
        locations: ``(Q, M, L, P, 2)`` normalised ``(u, v)`` (grid ``2 * loc - 1``, ``align_corners=False``,
            zero padding: the conventions of the other paths).
        weights: ``(Q, M, L, P)``.

    Returns:
        ``(Q, M, D)``. No input validation (the public functions validate, then call this).
    """
    q, m, _, p, _ = locations.shape
    out: Optional[Tensor] = None
    grid = 2.0 * locations - 1.0
    for lvl, val in enumerate(values):
        num_images, mv, d, h, w = val.shape
        g = grid[:, :, lvl]  # (Q, M, P, 2)
        wt = weights[:, :, lvl]  # (Q, M, P)
        if mv == 1:
            # one map for all heads: every head's points are extra grid columns, (I, Q, M * P, 2)
            gi = g.reshape(1, q, m * p, 2).expand(num_images, q, m * p, 2)
            s = F.grid_sample(val[:, 0], gi, mode="bilinear", padding_mode="zeros", align_corners=False)
            s = (s.view(num_images, d, q, m, p) * wt.view(1, 1, q, m, p)).sum(-1)  # (I, D, Q, M)
            s = s.permute(0, 2, 3, 1)  # (I, Q, M, D)
        else:
            # head m samples value head m: the heads are extra images, (I * M, Q, P, 2)
            gi = g.transpose(0, 1).unsqueeze(0).expand(num_images, m, q, p, 2).reshape(num_images * m, q, p, 2)
            s = F.grid_sample(val.reshape(num_images * m, d, h, w), gi, mode="bilinear", padding_mode="zeros",
                              align_corners=False)  # (I * M, d, Q, P)
            s = (s.view(num_images, m, d, q, p) * wt.permute(1, 0, 2).reshape(1, m, 1, q, p)).sum(-1)  # (I, M, d, Q)
            s = s.permute(0, 3, 1, 2)  # (I, Q, M, d)
        part = _select_image(s, image_index)
        out = part if out is None else out + part
    return out


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
