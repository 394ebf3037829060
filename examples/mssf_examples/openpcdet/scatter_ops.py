"""Pure-torch ``scatter_max`` for OpenPCDet's dynamic pillar VFEs where ``torch_scatter`` is not installed.

OpenPCDet's ``DynamicPillarVFESimple2D`` (VoxelNeXt-2D) pools the points of a pillar with
``torch_scatter.scatter_max`` (``PFNLayerV2``), a compiled package with no build for every torch (none for
the CPU torch of this project's environment). :func:`use_pure_torch_scatter` gives that module, and only
when ``torch_scatter`` does not import, a stand-in whose ``scatter_max`` is ``Tensor.scatter_reduce(...,
"amax")``: the same maxima (``[0]``, all OpenPCDet reads); the gradient of a tie is shared between the tied
points instead of going to one.
"""

from __future__ import annotations

import importlib
import types

from torch import Tensor

from mssf_blocks.errors import MSSFError

__all__ = ["scatter_max", "use_pure_torch_scatter"]


def scatter_max(src: Tensor, index: Tensor, dim: int = 0, dim_size: int | None = None) -> tuple[Tensor, None]:
    """``(out, None)``: ``out[j] = max(src[i] for index[i] == j)`` over rows (``dim=0``), zeros for empty ``j``.

    Args:
        src: ``(N, C)`` values; index: ``(N,)`` int row of each value; dim_size: rows of ``out``
            (default ``index.max() + 1``).
    """
    if dim != 0 or src.dim() != 2 or index.dim() != 1 or index.shape[0] != src.shape[0]:
        raise MSSFError(f"scatter_max: expected src (N, C), index (N,) and dim=0, got src {tuple(src.shape)}, "
                        f"index {tuple(index.shape)}, dim={dim}")
    n = int(index.max()) + 1 if dim_size is None and index.numel() else int(dim_size or 0)
    out = src.new_zeros((n, src.shape[1]))
    return out.scatter_reduce(0, index.long()[:, None].expand_as(src), src, "amax", include_self=False), None


def use_pure_torch_scatter() -> bool:
    """Give ``pcdet.models.backbones_3d.vfe.dynamic_pillar_vfe`` the stand-in when ``torch_scatter`` does not
    import; returns whether it did (idempotent)."""
    try:
        importlib.import_module("torch_scatter")
        return False
    except ImportError:
        pass
    from pcdet.models.backbones_3d.vfe import dynamic_pillar_vfe

    dynamic_pillar_vfe.torch_scatter = types.SimpleNamespace(scatter_max=scatter_max, __name__="pure-torch scatter")
    return True

