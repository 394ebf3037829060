"""Which execution path the blocks take: the eager fast paths, or the static-shape path.

The eager paths of the fusion blocks size some intermediates by the data (MSDFF's touched-pixel plans,
SFF's gathered corner pixels, the visible-voxel rows of the output norm, the centroid join's
``unique``). Graph capture cannot follow those sizes without a new graph per frame, and exporters need
a fixed set of operators, so while a graph is captured (:func:`~mssf_blocks.checks.tensors.is_tracing`) every
block takes its *static-shape path* instead: the same result from operators whose output sizes depend
on input sizes only (``grid_sample``, masks, sorts). :func:`static_path` forces it in eager mode too
(e.g. to check it against the eager path, or for CUDA graphs).

This module is the whole static-shape path: the switch (:func:`static_path`, :func:`use_static_path`),
the static formulations of the data-dependent steps (below), and the pytree registration that lets the
library's dataclasses be graph inputs and outputs (:func:`register_pytree`; ``docs/deployment.md``).
MSDFF's static sampling on the CPU samples the raw channels of every bilinear corner in fixed-size
embedding bags and projects per head (``functional/deform/bag.py``, ``sample_project_static``: a cost in
the voxels, not the pixels); on other devices and under an ONNX export (where ``embedding_bag`` would
become a ``Loop``) it is the sampling op's grid backend (``functional/deform/grid.py``: every pixel
projected, under ONNX by a 1 x 1 ``Conv``, then ``GridSample`` per head).
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator, List, Tuple

import torch
from torch import Tensor, nn

from mssf_blocks import torch_versions
from mssf_blocks.checks.tensors import is_tracing

__all__ = ["static_path", "use_static_path", "linear_norm_visible_static", "segment_slots", "register_pytree"]

_FORCED = [0]  # nesting depth of static_path() (a list: read by dynamo as a guarded global)


@contextlib.contextmanager
def static_path(enabled: bool = True) -> Iterator[None]:
    """Run the fusion blocks on their static-shape (compile- and export-friendly) path in this block.

    Example:
        >>> import torch
        >>> from mssf_blocks.functional import bilinear_sample
        >>> img, uv = torch.arange(4.0).view(1, 1, 2, 2), torch.tensor([[[0.75, 0.25]]])
        >>> with static_path():
        ...     bilinear_sample(img, uv, torch.tensor([0])).flatten().tolist()
        [1.0]
    """
    _FORCED[0] += 1 if enabled else 0
    try:
        yield
    finally:
        _FORCED[0] -= 1 if enabled else 0


def use_static_path() -> bool:
    """Whether the blocks take the static-shape path now (graph capture, or inside :func:`static_path`)."""
    return _FORCED[0] > 0 or is_tracing()


# --------------------------------------------------------------------------------------------------
# static formulations of the data-dependent steps
# --------------------------------------------------------------------------------------------------
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


# --------------------------------------------------------------------------------------------------
# pytree registration: the dataclasses as export inputs / outputs
# --------------------------------------------------------------------------------------------------
# torch.export and the dynamo ONNX exporter flatten their inputs and outputs with torch's pytree: the
# tensors of these dataclasses become graph inputs (in the order of the field lists below), the other
# fields (grid, sizes) become part of the graph's input spec, fixed at export time.
def register_pytree(cls: type, children: Tuple[str, ...], static: Tuple[str, ...]) -> type:
    """Register the dataclass ``cls`` with torch's pytree (export inputs / outputs): the fields ``children``
    (tensors, in this order) become graph inputs, the fields ``static`` the graph's fixed context. Records
    ``children`` as ``cls.PYTREE_FIELDS``; returns ``cls``."""
    cls.PYTREE_FIELDS = tuple(children)

    def get(obj: Any, f: str) -> Any:
        # sequences as lists (FusionInputs stores its levels as a tuple): the ONNX exporter turns the
        # tuples of a dynamic_shapes spec into lists before matching it against the inputs
        value = getattr(obj, f)
        return list(value) if isinstance(value, tuple) else value

    def flatten(obj: Any) -> Tuple[List[Any], Tuple[Any, ...]]:
        return [get(obj, f) for f in children], tuple(getattr(obj, f) for f in static)

    def flatten_with_keys(obj: Any):
        # MappingKey (obj['points']), not GetAttrKey (obj.points): torch 2.13's export guard code substitutes
        # paths as text, and obj.points is a prefix of obj.points_batch (a SyntaxError in ep.module()).
        return [(torch_versions.mapping_key(f), get(obj, f)) for f in children], tuple(getattr(obj, f) for f in static)

    def unflatten(values: List[Any], context: Tuple[Any, ...]) -> Any:
        kwargs = dict(zip(children, values))
        kwargs.update(zip(static, context))
        return cls(**kwargs)

    def to_dumpable(context: Tuple[Any, ...]) -> str:
        import json

        def dumpable(c: Any) -> Any:
            if hasattr(c, "point_cloud_range"):  # a VoxelGrid
                return {"voxel_size": list(c.voxel_size), "point_cloud_range": list(c.point_cloud_range)}
            return list(c) if isinstance(c, tuple) else c

        return json.dumps([dumpable(c) for c in context])

    def from_dumpable(text: str) -> Tuple[Any, ...]:
        import json

        from mssf_blocks.voxel_grid import VoxelGrid

        def loaded(c: Any) -> Any:
            if isinstance(c, dict):
                return VoxelGrid(**c)
            return tuple(c) if isinstance(c, list) else c

        return tuple(loaded(c) for c in json.loads(text))

    torch_versions.register_pytree_node(
        cls, flatten, unflatten, serialized_type_name=f"mssf_blocks.{cls.__name__}",
        flatten_with_keys=flatten_with_keys, to_dumpable=to_dumpable, from_dumpable=from_dumpable,
    )
    return cls
