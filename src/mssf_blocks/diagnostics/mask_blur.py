"""The "Mask Blur" oracle ablation: image features sampled by 3D blurred points are masked out.

Definitions in :mod:`mssf_blocks.diagnostics`; import these names from there.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Union

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_dtype, check_shape
from mssf_blocks.errors import MSSFError
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection
from mssf_blocks.diagnostics.classify import BlurClassification, _tensor

__all__ = ["mask_blur_valid", "mask_blur_projection", "mask_blurred_features"]


# -- mask blur --------------------------------------------------------------------------------------
def _check_blurred(blurred, n: int) -> Tensor:
    if isinstance(blurred, BlurClassification):
        blurred = blurred.blurred
    check_shape(blurred, "blurred", (n,))
    check_dtype(blurred, "blurred", (torch.bool,))
    return blurred


def mask_blur_valid(valid: Tensor, blurred: Union[Tensor, BlurClassification]) -> Tensor:
    """``(N, V)`` ``valid & ~blurred``: the sampling mask of the paper's "Mask Blur" ablation."""
    check_shape(valid, "valid", ("N", "V"))
    check_dtype(valid, "valid", (torch.bool,))
    return valid & ~_check_blurred(blurred, valid.shape[0]).to(valid.device)[:, None]


def mask_blur_projection(
    projection: CentroidProjection, blurred: Union[Tensor, BlurClassification]
) -> CentroidProjection:
    """A projection whose blurred rows sample no image feature ("Mask Blur", an oracle ablation).

    Blurred rows get ``valid = False`` and ``uv = -1`` (outside the image, so a sampler with zero
    padding reads zeros even if it ignores ``valid``). Pass the result to SFF/MSDFF instead of the
    original projection.
    """
    if not isinstance(projection, CentroidProjection):
        raise MSSFError(f"projection: expected a CentroidProjection, got {type(projection).__name__}")
    bl = _check_blurred(blurred, projection.uv.shape[0]).to(projection.uv.device)
    uv = torch.where(bl[:, None, None], torch.full_like(projection.uv, -1.0), projection.uv)
    return replace(projection, uv=uv, valid=projection.valid & ~bl[:, None])


def mask_blurred_features(features: Tensor, blurred: Union[Tensor, BlurClassification]) -> Tensor:
    """Zero the image features ``(N, C)`` or ``(N, V, C)`` sampled by blurred points (no gradient there)."""
    if _tensor(features, "features").dim() not in (2, 3):
        raise MSSFError(f"features: expected shape (N, C) or (N, V, C), got {tuple(features.shape)}")
    bl = _check_blurred(blurred, features.shape[0]).to(features.device)
    keep = ~bl.reshape((-1,) + (1,) * (features.dim() - 1))
    return torch.where(keep, features, torch.zeros_like(features))

