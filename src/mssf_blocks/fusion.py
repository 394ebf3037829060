"""Image samplers of the MSSF fusion blocks: SFF, MSDFF and the MSDFF query initialisation.

Paper: *MSSF*, Sec. III-C ("Voxel-Image Fusion Backbone"). Every voxel of a sparse tensor is projected
into the cameras (:class:`~mssf_blocks.geometry.VoxelCentroidProjector`, eq. 1-2) and one of the
operators below turns the multi-scale image features at that spot into a per-voxel image feature
``f_img`` with as many channels as the voxel feature (eq. 3); the fusion block then adds it,
``f_fuse = f_vox + f_img`` (eq. 5, :class:`~mssf_blocks.blocks.FusionBlock`).

* :class:`SFF` - simple feature fusion (eq. 6-7): bilinear sample of every level at the projected
  centroid, concatenation, ``Linear + BatchNorm1d``.
* :class:`MSDFF` - multi-scale deformable feature fusion (eq. 9-10): Deformable-DETR cross-attention
  with one query per voxel and the projected centroid as reference point, ``Linear + BatchNorm1d``.
* :class:`QueryInit` - the first MSDFF block's query (eq. 8): ``Linear_BN(cat(f_vox, f_img^1, p))``.

Conventions shared by all three (``docs/fusion.md`` has the details):

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

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple, Type

import torch
from torch import Tensor, nn

from ._checks import (
    check_floating,
    check_image_size,
    check_points,
    check_positive_int,
    check_shape,
    to_module_dtype,
)
from ._consistency import check_agreement, check_batch_statistics, check_channels, level_batch_entries
from ._fusion_utils import (
    _autocast_off,
    _corner_aligned_uv,
    _check_projection,
    _factory,
    _linear_bn_visible,
    _norm,
    _sampling_dtype,
    _to_sampling_dtype,
    check_image_features,
)
from ._sanity import check_level_sizes
from .errors import MSSFError
from .functional.geometry import normalize_lidar2img
from .functional.sampling import bilinear_sample, camera_mean
from .geometry import CentroidProjection
from .msdff import MSDFF

__all__ = [
    "FusionInputs",
    "SFF",
    "MSDFF",
    "QueryInit",
    "check_image_features",
    "sample_at_projection",
]



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
# inputs of a fusion block
# ---------------------------------------------------------------------------------------------------
def check_input_agreement(image_features, lidar2img: Tensor, l2i: Tensor, points_to_sensor) -> None:
    """The batch size (and the cameras) of the camera inputs agree; else the error names the argument most
    of the others disagree with, with both shapes (shapes only). On a tie in the batch size the image levels
    win: they come out of a network run on the whole batch, while ``lidar2img`` / ``points_to_sensor`` are
    assembled by hand."""
    # (with several cameras a 4-d level is wrong whatever its batch, folded (B*V, C, H, W) most likely:
    # check_image_features says so, instead of a batch-size vote)
    ndims = (4, 5) if l2i.shape[1] == 1 else (5,)
    entries = level_batch_entries(image_features, ndims=ndims) + [("lidar2img", l2i.shape[0], tuple(lidar2img.shape))]
    if isinstance(points_to_sensor, Tensor) and points_to_sensor.dim() == 3:
        entries.append(("points_to_sensor", points_to_sensor.shape[0], tuple(points_to_sensor.shape)))
    check_agreement(entries, "batch size")
    # Cameras: lidar2img wins a tie (one matrix per camera of the set-up). 4-d levels are
    # one camera each: check_image_features names that case.
    check_agreement([("lidar2img", l2i.shape[1], tuple(lidar2img.shape))]
                    + level_batch_entries(image_features, dim=1, ndims=(5,)), "number of cameras V")


@dataclass(frozen=True, eq=False)
class FusionInputs:
    """The camera side of a fusion block: image features plus what projection needs.

    Attributes:
        image_features: ``L`` levels, each ``(B, C_l, H_l, W_l)`` or ``(B, V, C_l, H_l, W_l)``.
        lidar2img: ``(B, V, 3, 4)`` (or ``(B, 3, 4)`` for one camera) sensor-to-pixel matrices.
        image_size: ``(H, W)`` of the image the features were computed from.
        points: ``(P, 3)`` raw x, y, z (for voxel centroids); other columns are refused (slice them
            off: ``pts[:, :3]``, or ``pts[:, 1:4]`` for OpenPCDet's ``(b, x, y, z, ...)``).
        points_batch: ``(P,)`` integer batch index of every point.
        points_to_sensor: optional ``(B, 4, 4)`` inverse of the point-cloud augmentation.

    Raises:
        MSSFError: levels with different batch sizes or cameras, ``V`` not matching ``lidar2img``, a
            level that is not 4-d or 5-d, a bad ``image_size`` (also one whose aspect disagrees with
            level 0's by more than one level-0 pixel, e.g. a swapped ``(W, H)``), ``points`` that are not
            ``(P, 3)``.
    """

    image_features: Sequence[Tensor]
    lidar2img: Tensor
    image_size: Tuple[int, int]
    points: Tensor
    points_batch: Tensor
    points_to_sensor: Optional[Tensor] = None

    def __post_init__(self) -> None:
        l2i = normalize_lidar2img(self.lidar2img)
        check_input_agreement(self.image_features, self.lidar2img, l2i, self.points_to_sensor)
        levels = check_image_features(
            self.image_features, "image_features", batch_size=l2i.shape[0], num_cameras=l2i.shape[1]
        )
        # Every level is the image over a stride, finest first; a channels-last level is named.
        check_level_sizes(levels, self.image_size)
        # The levels know the image's aspect: a swapped (W, H) would silently move every sampling spot.
        h, w = check_image_size(self.image_size, levels[0].shape[-2:])
        object.__setattr__(self, "image_size", (h, w))
        object.__setattr__(self, "image_features", tuple(self.image_features))
        check_points(self.points, self.points_batch, exact_xyz=True)

    @property
    def batch_size(self) -> int:
        return int(self.image_features[0].shape[0])

    @property
    def num_cameras(self) -> int:
        return int(normalize_lidar2img(self.lidar2img).shape[1])


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
            different fraction of a pixel; :mod:`mssf_blocks.compat.mssf_official`).
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
        >>> from mssf_blocks.geometry import CentroidProjection
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
_QUERY_POSITIONS = ("voxel_centre", "centroid")


class QueryInit(nn.Module):
    """MSDFF query initialisation (paper eq. 8): ``Linear_BN(cat(f_vox, f_img^1, p))``.

    Args:
        voxel_channels: ``C_v`` of ``f_vox``.
        image_channels: ``C_i`` of ``f_img^1`` (the first image level sampled at the centroid).
        out_channels: query channels (the MSDFF ``embed_dim``).
        point_cloud_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` used to normalise voxel
            centres to ``p`` in ``[0, 1]^3``.
        norm_layer: normalisation after the linear layer (``None``: none).
        device, dtype: factory arguments of the parameters.
        position: what :class:`~mssf_blocks.blocks.FusionBlock` passes as ``centers``:
            ``"voxel_centre"`` (default; the paper's eq. 8 position of the voxel) or ``"centroid"`` (the
            centroid of the voxel's points, its centre where it holds none: the MSSF authors' code).
        align_corners: how :class:`~mssf_blocks.blocks.FusionBlock` samples ``f_img^1``: as
            :func:`sample_at_projection` (``True``: the authors' ``align_corners=True``).

    The columns of ``linear.weight`` are ``[f_vox | f_img^1 | p]``; the authors' ``query_proj`` reads
    ``[f_img^1 | f_vox | p]`` (:mod:`mssf_blocks.compat.mssf_official` permutes them on loading).

    Shapes:
        - f_vox ``(N, C_v)``, f_img0 ``(N, C_i)``, centers ``(N, 3)`` metric ``(x, y, z)``.
        - output ``(N, out_channels)`` in the parameters' dtype; ``f_vox`` and ``f_img0`` of lower
          precision are read in it, float64 ones into a non-float64 module are refused
          (``docs/conventions.md``, "Dtypes").

    No host synchronisation in forward or backward.
    """

    def __init__(
        self,
        voxel_channels: int,
        image_channels: int,
        out_channels: int,
        point_cloud_range: Sequence[float],
        norm_layer: Optional[Type[nn.Module]] = nn.BatchNorm1d,
        device=None,
        dtype=None,
        position: str = "voxel_centre",
        align_corners: bool = False,
    ) -> None:
        super().__init__()
        if position not in _QUERY_POSITIONS:
            raise MSSFError(f"position: expected one of {_QUERY_POSITIONS}, got {position!r}")
        if not isinstance(align_corners, bool):
            raise MSSFError(f"align_corners: expected a bool, got {align_corners!r}")
        self.position, self.align_corners = position, align_corners
        self.voxel_channels = check_positive_int(voxel_channels, "voxel_channels")
        self.image_channels = check_positive_int(image_channels, "image_channels")
        self.out_channels = check_positive_int(out_channels, "out_channels")
        if isinstance(point_cloud_range, Tensor):
            point_cloud_range = point_cloud_range.detach().cpu().tolist()
        try:
            pcr = tuple(float(x) for x in point_cloud_range)
        except (TypeError, ValueError):
            raise MSSFError(f"point_cloud_range: expected 6 numbers, got {point_cloud_range!r}") from None
        if len(pcr) != 6 or not all(math.isfinite(x) for x in pcr) or not all(
            pcr[i + 3] > pcr[i] for i in range(3)
        ):
            raise MSSFError(
                "point_cloud_range: expected 6 finite numbers (x_min, y_min, z_min, x_max, y_max, z_max) "
                f"with max > min, got {point_cloud_range!r}"
            )
        self.point_cloud_range = pcr
        factory = _factory(device, dtype)
        self.linear = nn.Linear(self.voxel_channels + self.image_channels + 3, self.out_channels, **factory)
        self.norm = _norm(norm_layer, self.out_channels, factory)

    def normalized_centers(self, centers: Tensor) -> Tensor:
        """``p = (centers - min) / (max - min)``, ``(N, 3)``."""
        lo = centers.new_tensor(self.point_cloud_range[:3])
        hi = centers.new_tensor(self.point_cloud_range[3:])
        return (centers - lo) / (hi - lo)

    def forward(self, f_vox: Tensor, f_img0: Tensor, centers: Tensor) -> Tensor:
        dims = {}
        check_channels(f_vox, "f_vox", self.voxel_channels, "QueryInit voxel_channels")
        check_channels(f_img0, "f_img0", self.image_channels, "QueryInit image_channels")
        check_shape(f_vox, "f_vox", ("N", self.voxel_channels), dims)
        check_shape(f_img0, "f_img0", ("N", self.image_channels), dims)
        check_shape(centers, "centers", ("N", 3), dims)
        # The library's dtype rule: inputs are read in the parameters' dtype, float64 into a lower-precision
        # module is refused; the centres are positions (float32 or float64, rounded like any geometry).
        dtype = self.linear.weight.dtype
        f_vox = to_module_dtype(f_vox, "f_vox", dtype, "QueryInit")
        f_img0 = to_module_dtype(f_img0, "f_img0", dtype, "QueryInit")
        check_floating(centers, "centers")
        p = self.normalized_centers(centers.to(dtype))
        # (every voxel gets a query, seen or not: the norm takes all N rows)
        check_batch_statistics(self.norm, f_vox.shape[0], "f_vox", "exactly one voxel (N = 1)", "QueryInit")
        return self.norm(self.linear(torch.cat([f_vox, f_img0, p], dim=1)))

    def extra_repr(self) -> str:
        return (
            f"voxel_channels={self.voxel_channels}, image_channels={self.image_channels}, "
            f"out_channels={self.out_channels}, point_cloud_range={self.point_cloud_range}, "
            f"position={self.position!r}, align_corners={self.align_corners}"
        )
