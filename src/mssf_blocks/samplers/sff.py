"""``SFF``: simple feature fusion (paper eq. 6-7), and the sampling of one level at a projection.

Paper: *MSSF*, Sec. III-C ("Voxel-Image Fusion Backbone"). Every voxel of a sparse tensor is projected
into the cameras (:class:`~mssf_blocks.geometry.VoxelCentroidProjector`, eq. 1-2) and an image sampler
turns the multi-scale image features at that spot into a per-voxel image feature ``f_img`` with as many
channels as the voxel feature (eq. 3); the fusion block then adds it, ``f_fuse = f_vox + f_img`` (eq. 5,
:class:`~mssf_blocks.blocks.FusionBlock`). The samplers are :class:`SFF` (this module: bilinear sample
of every level at the projected centroid, concatenation, ``Linear + BatchNorm1d``),
:class:`~mssf_blocks.samplers.MSDFF` (eq. 9-10) and the MSDFF query,
:class:`~mssf_blocks.samplers.QueryInit` (eq. 8).

Conventions shared by the samplers (``docs/fusion.md`` has the details):

* image features are a sequence of ``L`` levels, each ``(B, C_l, H_l, W_l)`` (one camera) or
  ``(B, V, C_l, H_l, W_l)``; normalised ``uv`` is relative to the full image (``(u + 0.5) / W``), read
  with ``align_corners=False`` bilinear sampling and zero padding;
* a voxel is sampled in every camera where its projection is valid and the per-camera results are
  averaged; a voxel valid in no camera gets ``f_img = 0`` exactly (no bias, no normalisation shift), so
  the fusion block passes its voxel feature through unchanged, and it sends no gradient to the image;
* the ``Linear + BatchNorm1d`` output stage runs on the voxels seen by at least one camera only, so the
  batch statistics are those of real image features;
* the sampling (``uv``, MSDFF's locations and attention weights, the bilinear sums) runs in float32, or
  in float64 for a float64 module, never in half precision, also under ``torch.autocast``: image levels
  in float16 / bfloat16 are read as float32, and ``uv`` is converted to the sampling dtype.
"""

from __future__ import annotations

from typing import Optional, Sequence, Type

import torch
from torch import Tensor, nn

from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.samplers._layers import (
    _autocast_off,
    _corner_aligned_uv,
    _factory,
    _linear_bn_visible,
    _norm,
    _sampling_dtype,
    _to_sampling_dtype,
)
from mssf_blocks.checks.image_features import _check_projection, check_image_features
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.sampling import bilinear_sample, camera_mean
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection

__all__ = ["SFF", "sample_at_projection"]


def sample_at_projection(image_feature: Tensor, projection: CentroidProjection, align_corners: bool = False) -> Tensor:
    """Bilinear sample of one level at every voxel's projection, averaged over its valid cameras.

    This is ``Sample(F_I,i, c_img)`` of the paper (eq. 6) with the multi-camera mean.

    Args:
        image_feature: ``(B, C, H, W)`` or ``(B, V, C, H, W)``.
        projection: :class:`~mssf_blocks.geometry.CentroidProjection` with ``uv (N, V, 2)``,
            ``valid (N, V)``, ``batch_index (N,)``.
        align_corners: ``False`` (default, the library's convention): pixel ``x = u_norm * W - 0.5``.
            ``True``: ``x = u_norm * (W - 1)``, what ``F.grid_sample(align_corners=True)`` reads (the
            MSSF authors' SFF and query initialisation).

    Returns:
        ``(N, C)`` in float32 (float64 for a float64 level); zeros (and no gradient into the image) for
        voxels valid in no camera.
    """
    (level,) = check_image_features([image_feature], name="image_feature")
    uv, valid, batch_index = _check_projection(projection, level.shape[0], level.shape[1])
    dtype = _sampling_dtype(level)
    uv = uv.to(dtype)
    if align_corners:
        uv = _corner_aligned_uv(uv, level.shape[-2], level.shape[-1])
    with _autocast_off(level.device.type):
        return _mean_of_samples(bilinear_sample(level.to(dtype), uv, batch_index, valid), valid)


def _mean_of_samples(sampled: Tensor, valid: Tensor) -> Tensor:
    """:func:`camera_mean` of :func:`bilinear_sample`'s ``(N, V, C)`` output, whose unseen entries are
    exact zeros already: with one camera, the samples themselves (no pass over them)."""
    return sampled[:, 0] if sampled.shape[1] == 1 else camera_mean(sampled, valid)



# ---------------------------------------------------------------------------------------------------
# SFF
# ---------------------------------------------------------------------------------------------------
class SFF(nn.Module):
    """Simple feature fusion (paper eq. 6-7): ``Linear_BN(cat_l Sample(F_l, c_img))``.

    Args:
        in_channels: ``C_l`` of every image level (``L = len(in_channels)``).
        out_channels: channels of ``f_img`` (the voxel feature's channels in a fusion block).
        norm_layer: normalisation applied after the linear layer (``None``: none).
        align_corners: ``False`` (default): sample at pixel ``x = u_norm * W_l - 0.5`` (every level reads
            the same physical spot). ``True``: ``x = u_norm * (W_l - 1)``, ``F.grid_sample``'s
            ``align_corners=True`` as the MSSF authors' ``VoxelFusion`` samples (each level shifted by a
            different fraction of a pixel; :mod:`mssf_blocks.weights.authors_checkpoint`).
        device, dtype: factory arguments of the parameters.

    Shapes:
        - image_features: ``L`` levels ``(B, C_l, H_l, W_l)`` or ``(B, V, C_l, H_l, W_l)``.
        - projection: ``uv (N, V, 2)``, ``valid (N, V)``, ``batch_index (N,)``.
        - output: ``(N, out_channels)``; exact zeros for voxels seen by no camera.

    The sampling runs in float32 (float64 for a float64 module), also under ``torch.autocast``;
    float16 / bfloat16 levels are read as float32.

    Host synchronisation (what stalls a GPU): the projection's batch-index range check (one read-back)
    and which voxels are visible (``nonzero``; the BatchNorm runs on the visible rows, a
    data-dependent size). Both inherent; the backward has none.

    Example:
        >>> import torch
        >>> from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection
        >>> sff = SFF([4, 8], 16).eval()
        >>> feats = [torch.randn(1, 4, 8, 8), torch.randn(1, 8, 4, 4)]
        >>> proj = CentroidProjection(uv=torch.rand(5, 1, 2), depth=torch.ones(5, 1),
        ...     valid=torch.ones(5, 1, dtype=torch.bool), centroid=torch.zeros(5, 3),
        ...     has_points=torch.ones(5, dtype=torch.bool), batch_index=torch.zeros(5, dtype=torch.long))
        >>> sff(feats, proj).shape
        torch.Size([5, 16])
    """

    def __init__(
        self,
        in_channels: Sequence[int],
        out_channels: int,
        norm_layer: Optional[Type[nn.Module]] = nn.BatchNorm1d,
        device=None,
        dtype=None,
        align_corners: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(align_corners, bool):
            raise MSSFError(f"align_corners: expected a bool, got {align_corners!r}")
        self.align_corners = align_corners
        if isinstance(in_channels, int) or not isinstance(in_channels, Sequence) or len(in_channels) == 0:
            raise MSSFError(f"in_channels: expected a non-empty sequence of ints (one per level), got {in_channels!r}")
        self.in_channels = tuple(check_positive_int(c, f"in_channels[{i}]") for i, c in enumerate(in_channels))
        self.out_channels = check_positive_int(out_channels, "out_channels")
        factory = _factory(device, dtype)
        self.linear = nn.Linear(sum(self.in_channels), self.out_channels, **factory)
        self.norm = _norm(norm_layer, self.out_channels, factory)

    @property
    def num_levels(self) -> int:
        return len(self.in_channels)

    def sample(self, image_features: Sequence[Tensor], projection: CentroidProjection) -> Tensor:
        """The raw concatenated samples ``cat_l Sample(F_l, c_img)``, ``(N, sum C_l)``, camera-averaged.

        In float32 (float64 for a float64 module), whatever the levels' precision (see the module doc).
        """
        levels = check_image_features(image_features, channels=self.in_channels, channels_name="SFF in_channels[{l}]")
        uv, valid, batch_index = _check_projection(projection, levels[0].shape[0], levels[0].shape[1])
        dtype = _sampling_dtype(self.linear.weight)
        uv = uv.to(dtype)
        with _autocast_off(uv.device.type):
            parts = [
                _mean_of_samples(bilinear_sample(_to_sampling_dtype(lvl, dtype, f"image_features[{i}]", "SFF"),
                                                 _corner_aligned_uv(uv, *lvl.shape[-2:]) if self.align_corners else uv,
                                                 batch_index, valid), valid)
                for i, lvl in enumerate(levels)
            ]
            return torch.cat(parts, dim=1)

    def forward(self, image_features: Sequence[Tensor], projection: CentroidProjection) -> Tensor:
        sampled = self.sample(image_features, projection).to(self.linear.weight.dtype)
        return _linear_bn_visible(self.linear, self.norm, sampled, projection.valid.any(dim=1))

    def extra_repr(self) -> str:
        extra = ", align_corners=True" if self.align_corners else ""
        return f"in_channels={self.in_channels}, out_channels={self.out_channels}{extra}"


# ---------------------------------------------------------------------------------------------------
# QueryInit
# ---------------------------------------------------------------------------------------------------
