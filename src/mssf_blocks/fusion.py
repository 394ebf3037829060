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

import contextlib
import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple, Type, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ._checks import (
    autocast_on,
    check_dtype,
    check_floating,
    check_index_range,
    check_positive_int,
    check_shape,
)
from .errors import MSSFError
from .functional.geometry import normalize_lidar2img
from .functional.sampling import bilinear_sample, camera_mean, ms_deform_sample, ms_deform_sample_project
from .geometry import CentroidProjection

__all__ = [
    "FusionInputs",
    "SFF",
    "MSDFF",
    "QueryInit",
    "check_image_features",
    "sample_at_projection",
]

_INT_DTYPES = (torch.int32, torch.int64)
_METHODS = ("auto", "reference", "fast")
_VALUE_PROJECTIONS = ("after_sampling", "before_sampling")


# ---------------------------------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------------------------------
def check_image_features(
    image_features: Sequence[Tensor],
    name: str = "image_features",
    num_levels: Optional[int] = None,
    channels: Optional[Sequence[int]] = None,
    batch_size: Optional[int] = None,
    num_cameras: Optional[int] = None,
) -> List[Tensor]:
    """Validate multi-scale image features and return them as ``(B, V, C_l, H_l, W_l)`` views.

    Args:
        image_features: ``L`` levels, each ``(B, C_l, H_l, W_l)`` (V = 1) or ``(B, V, C_l, H_l, W_l)``.
        name: argument name used in error messages (``image_features[l]`` names a level).
        num_levels: expected ``L`` (``None``: any ``L >= 1``).
        channels: expected ``C_l`` of every level.
        batch_size: expected ``B``.
        num_cameras: expected ``V``.

    Returns:
        The levels as 5-d ``(B, V, C_l, H_l, W_l)`` tensors (views, no copy).

    Raises:
        MSSFError: naming the level, the expected and the received shape.
    """
    if isinstance(image_features, Tensor) or not isinstance(image_features, Sequence):
        raise MSSFError(
            f"{name}: expected a sequence (list/tuple) of level tensors (B, C_l, H_l, W_l) or "
            f"(B, V, C_l, H_l, W_l), got {type(image_features).__name__}"
            + (f" of shape {tuple(image_features.shape)} (wrap a single level in a list)"
               if isinstance(image_features, Tensor) else "")
        )
    if len(image_features) == 0:
        raise MSSFError(f"{name}: expected at least one level, got an empty sequence")
    if num_levels is not None and len(image_features) != num_levels:
        raise MSSFError(f"{name}: expected {num_levels} levels (num_levels), got {len(image_features)}")
    if channels is not None and len(channels) != len(image_features):
        raise MSSFError(
            f"{name}: expected {len(channels)} levels with channels {tuple(channels)}, "
            f"got {len(image_features)} levels"
        )
    dims = {}
    if batch_size is not None:
        dims["B"] = int(batch_size)
    if num_cameras is not None:
        dims["V"] = int(num_cameras)
    out = []
    dtype = None
    for l, level in enumerate(image_features):
        lname = f"{name}[{l}]"
        if not isinstance(level, Tensor):
            raise MSSFError(f"{lname}: expected a torch.Tensor, got {type(level).__name__}")
        c = None if channels is None else int(channels[l])
        if level.dim() == 4:
            check_shape(level, lname, ("B", c, None, None), dims)
            if dims.setdefault("V", 1) != 1:
                raise MSSFError(
                    f"{lname}: a 4-d level (B, C, H, W) means one camera, but V={dims['V']} "
                    f"(from lidar2img or another level); pass (B, V, C, H, W), got shape {tuple(level.shape)}"
                )
            level = level[:, None]
        elif level.dim() == 5:
            check_shape(level, lname, ("B", "V", c, None, None), dims)
        else:
            raise MSSFError(
                f"{lname}: expected shape (B, C_l, H_l, W_l) or (B, V, C_l, H_l, W_l), "
                f"got shape {tuple(level.shape)}"
            )
        check_floating(level, lname)
        if level.shape[-1] == 0 or level.shape[-2] == 0:
            raise MSSFError(f"{lname}: expected a non-empty feature map, got shape {tuple(level.shape)}")
        if dtype is None:
            dtype = level.dtype
        elif level.dtype != dtype:
            raise MSSFError(f"{lname}: expected dtype {dtype} (as {name}[0]), got {level.dtype}")
        out.append(level)
    return out


def _check_projection(projection: CentroidProjection, batch_size: int, num_cameras: int,
                      name: str = "projection") -> Tuple[Tensor, Tensor, Tensor]:
    for attr in ("uv", "valid", "batch_index"):
        if not hasattr(projection, attr):
            raise MSSFError(
                f"{name}: expected a CentroidProjection (with .{attr}), got {type(projection).__name__}"
            )
    dims = {"V": num_cameras}
    uv = check_shape(projection.uv, f"{name}.uv", ("N", "V", 2), dims)
    check_floating(uv, f"{name}.uv")
    valid = check_shape(projection.valid, f"{name}.valid", ("N", "V"), dims)
    check_dtype(valid, f"{name}.valid", (torch.bool,))
    batch_index = check_shape(projection.batch_index, f"{name}.batch_index", ("N",), dims)
    check_dtype(batch_index, f"{name}.batch_index", _INT_DTYPES)
    check_index_range(batch_index, f"{name}.batch_index", batch_size, "image batch size B")
    return uv, valid, batch_index.long()


def _norm(norm_layer: Type[nn.Module], channels: int, factory: dict) -> nn.Module:
    # Factory kwargs only when given, so norm layers without device/dtype arguments still work.
    return norm_layer(channels, **factory) if factory else norm_layer(channels)


def _factory(device, dtype) -> dict:
    return {k: v for k, v in (("device", device), ("dtype", dtype)) if v is not None}


def _sampling_dtype(param_or_tensor: Tensor) -> torch.dtype:
    """float64 for float64, else float32: the dtype image sampling runs in (never half precision).

    A normalised coordinate in bfloat16 has a resolution of 2^-8 near 1, about 4 pixels of a
    1,000-pixel-wide level; in float16, 2^-11 (half a pixel).
    """
    return torch.float64 if param_or_tensor.dtype == torch.float64 else torch.float32


def _to_sampling_dtype(x: Tensor, dtype: torch.dtype, name: str, owner: str) -> Tensor:
    """``x`` converted up to the sampling ``dtype`` (float16 / bfloat16 / float32 -> float32 / float64).

    A float64 ``x`` for a float32 sampling is refused rather than rounded: the module is float32.
    """
    if x.dtype == dtype:
        return x
    if x.dtype == torch.float64:
        raise MSSFError(
            f"{name}: expected dtype {dtype} or lower (the precision {owner} samples in with its "
            f"parameters), got torch.float64; convert the module with .double() or the tensor with .float()"
        )
    return x.to(dtype)


def _autocast_off(device_type: str):
    """A context that disables autocast for ``device_type`` when it is on (else does nothing)."""
    return torch.autocast(device_type, enabled=False) if autocast_on(device_type) else contextlib.nullcontext()


def _linear_bn_visible(linear: nn.Module, norm: nn.Module, x: Tensor, visible: Tensor) -> Tensor:
    """``norm(linear(x))`` on the visible rows, exact zeros elsewhere (the fusion adds nothing there)."""
    rows = visible.nonzero().squeeze(1)
    if rows.numel() == x.shape[0]:  # every voxel seen (the usual case): no gather / scatter copies
        return norm(linear(x))
    y = norm(linear(x[rows]))
    out = y.new_zeros(x.shape[0], y.shape[1])
    return out.index_put((rows,), y)


def sample_at_projection(image_feature: Tensor, projection: CentroidProjection) -> Tensor:
    """Bilinear sample of one level at every voxel's projection, averaged over its valid cameras.

    This is ``Sample(F_I,i, c_img)`` of the paper (eq. 6) with the multi-camera mean.

    Args:
        image_feature: ``(B, C, H, W)`` or ``(B, V, C, H, W)``.
        projection: :class:`~mssf_blocks.geometry.CentroidProjection` with ``uv (N, V, 2)``,
            ``valid (N, V)``, ``batch_index (N,)``.

    Returns:
        ``(N, C)`` in float32 (float64 for a float64 level); zeros (and no gradient into the image) for
        voxels valid in no camera.
    """
    (level,) = check_image_features([image_feature], name="image_feature")
    uv, valid, batch_index = _check_projection(projection, level.shape[0], level.shape[1])
    dtype = _sampling_dtype(level)
    with _autocast_off(level.device.type):
        return camera_mean(bilinear_sample(level.to(dtype), uv.to(dtype), batch_index, valid), valid)


# ---------------------------------------------------------------------------------------------------
# inputs of a fusion block
# ---------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class FusionInputs:
    """The camera side of a fusion block: image features plus what projection needs.

    Attributes:
        image_features: ``L`` levels, each ``(B, C_l, H_l, W_l)`` or ``(B, V, C_l, H_l, W_l)``.
        lidar2img: ``(B, V, 3, 4)`` (or ``(B, 3, 4)`` for one camera) sensor-to-pixel matrices.
        image_size: ``(H, W)`` of the image the features were computed from.
        points: ``(P, 3+)`` raw points (for voxel centroids).
        points_batch: ``(P,)`` integer batch index of every point.
        points_to_sensor: optional ``(B, 4, 4)`` inverse of the point-cloud augmentation.

    Raises:
        MSSFError: levels with different batch sizes or cameras, ``V`` not matching ``lidar2img``, a
            level that is not 4-d or 5-d, a bad ``image_size``.
    """

    image_features: Sequence[Tensor]
    lidar2img: Tensor
    image_size: Tuple[int, int]
    points: Tensor
    points_batch: Tensor
    points_to_sensor: Optional[Tensor] = None

    def __post_init__(self) -> None:
        l2i = normalize_lidar2img(self.lidar2img)
        check_image_features(
            self.image_features, "image_features", batch_size=l2i.shape[0], num_cameras=l2i.shape[1]
        )
        try:
            h, w = (int(s) for s in self.image_size)
        except (TypeError, ValueError):
            raise MSSFError(f"image_size: expected (H, W), got {self.image_size!r}") from None
        if h <= 0 or w <= 0:
            raise MSSFError(f"image_size: expected positive (H, W), got {self.image_size!r}")
        object.__setattr__(self, "image_size", (h, w))
        object.__setattr__(self, "image_features", tuple(self.image_features))
        check_shape(self.points, "points", ("P", None))
        check_shape(self.points_batch, "points_batch", (self.points.shape[0],))

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
        norm_layer: normalisation applied after the linear layer.
        device, dtype: factory arguments of the parameters.

    Shapes:
        - image_features: ``L`` levels ``(B, C_l, H_l, W_l)`` or ``(B, V, C_l, H_l, W_l)``.
        - projection: ``uv (N, V, 2)``, ``valid (N, V)``, ``batch_index (N,)``.
        - output: ``(N, out_channels)``; exact zeros for voxels seen by no camera.

    The sampling runs in float32 (float64 for a float64 module), also under ``torch.autocast``;
    float16 / bfloat16 levels are read as float32.

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
        norm_layer: Type[nn.Module] = nn.BatchNorm1d,
        device=None,
        dtype=None,
    ) -> None:
        super().__init__()
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
        levels = check_image_features(image_features, num_levels=self.num_levels, channels=self.in_channels)
        uv, valid, batch_index = _check_projection(projection, levels[0].shape[0], levels[0].shape[1])
        dtype = _sampling_dtype(self.linear.weight)
        uv = uv.to(dtype)
        with _autocast_off(uv.device.type):
            parts = [
                camera_mean(bilinear_sample(_to_sampling_dtype(lvl, dtype, f"image_features[{i}]", "SFF"), uv,
                                            batch_index, valid), valid)
                for i, lvl in enumerate(levels)
            ]
            return torch.cat(parts, dim=1)

    def forward(self, image_features: Sequence[Tensor], projection: CentroidProjection) -> Tensor:
        sampled = self.sample(image_features, projection).to(self.linear.weight.dtype)
        return _linear_bn_visible(self.linear, self.norm, sampled, projection.valid.any(dim=1))

    def extra_repr(self) -> str:
        return f"in_channels={self.in_channels}, out_channels={self.out_channels}"


# ---------------------------------------------------------------------------------------------------
# MSDFF
# ---------------------------------------------------------------------------------------------------
class MSDFF(nn.Module):
    """Multi-scale deformable feature fusion (paper eq. 9-10), Deformable-DETR cross-attention.

    For every voxel query ``q`` and every camera where the voxel projects validly to ``c_img``:

    * ``o = sampling_offsets(q)`` viewed ``(M, L, P, 2)``, sampling location
      ``c_img + o / (W_l, H_l)`` (eq. 9);
    * ``w = softmax over the L*P slots of attention_weights(q)`` per head;
    * head ``m`` reads ``sum_{l,p} w * Sample(value_proj_m(F_l), location)``;

    heads are concatenated, averaged over the valid cameras, and ``Linear_BN`` = ``output_proj`` + norm
    gives ``f_img`` (eq. 10). Sampling is linear in the values, so the value projection may be applied
    to the pixels (all of them, or only those a bilinear corner reads) or after sampling (raw channels
    sampled per head, projected with that head's rows of ``value_proj.weight``, plus
    ``value_proj.bias`` times the in-image bilinear weight mass): all are exactly equal, and the
    default ``method="auto"`` picks the cheapest per level, at a cost that scales with the pixels the
    voxels read, not with the image.

    Args:
        embed_dim: query and output channels ``E`` (the voxel channels); divisible by ``num_heads``.
        value_channels: channels of the image levels; all levels must have the same (FPN) channels,
            an int or a sequence of equal ints.
        num_heads: ``M``.
        num_levels: ``L``, number of image levels read.
        num_points: ``P``, sampling points per head and level.
        norm_layer: normalisation after ``output_proj``.
        method: ``"auto"`` (default): whatever ``value_projection``, per level the cheapest exact plan
            of :func:`~mssf_blocks.functional.ms_deform_sample_project` ``method="touched"`` (project
            every pixel, project only the ``U_l`` pixels some bilinear corner reads, or sample those
            pixels' raw channels and project per head; cost
            ``O(min(pixels_l * E, U_l * (E + G), U_l * G + N * M * P * 4 * B) * C)``, see
            ``docs/fusion.md``). ``"fast"`` / ``"reference"``: the literal order of
            ``value_projection`` with ``ms_deform_sample``'s embedding-bag / ``grid_sample`` path.
        value_projection: the order used by ``method`` ``"fast"`` / ``"reference"``:
            ``"after_sampling"`` (default; sample the raw channels per head, then project; cost
            ``O(N * M * L * P * C)``, independent of the image size) or ``"before_sampling"``
            (Deformable DETR's order: ``value_proj`` on every pixel, then sample ``E / M`` channels per
            head; ``O(pixels * C * E + N * M * L * P * E / M)``). All give the same result (tested).
        device, dtype: factory arguments of the parameters.

    Shapes:
        - query: ``(N, E)``; image_features: ``L`` levels ``(B, [V,] C, H_l, W_l)``;
          projection: ``uv (N, V, 2)``, ``valid (N, V)``, ``batch_index (N,)``.
        - output: ``(N, E)``; exact zeros for voxels seen by no camera.

    Precision: the locations, attention weights and sampling run in float32 (float64 for a float64
    module), also under ``torch.autocast``; float16 / bfloat16 levels are read as float32
    (``docs/fusion.md``, "Precision and mixed-precision training").

    Parameter names and shapes are those of Deformable DETR's ``MSDeformAttn`` (``sampling_offsets``,
    ``attention_weights``, ``value_proj``, ``output_proj``), so pretrained weights map across; the norm
    is ``norm``.
    """

    def __init__(
        self,
        embed_dim: int,
        value_channels: Union[int, Sequence[int]],
        num_heads: int = 8,
        num_levels: int = 4,
        num_points: int = 4,
        norm_layer: Type[nn.Module] = nn.BatchNorm1d,
        method: str = "auto",
        value_projection: str = "after_sampling",
        device=None,
        dtype=None,
    ) -> None:
        super().__init__()
        self.embed_dim = check_positive_int(embed_dim, "embed_dim")
        self.num_heads = check_positive_int(num_heads, "num_heads")
        self.num_levels = check_positive_int(num_levels, "num_levels")
        self.num_points = check_positive_int(num_points, "num_points")
        if self.embed_dim % self.num_heads:
            raise MSSFError(
                f"embed_dim: expected a multiple of num_heads={self.num_heads}, got {self.embed_dim}"
            )
        if isinstance(value_channels, int):
            self.value_channels = check_positive_int(value_channels, "value_channels")
        else:
            chans = tuple(check_positive_int(c, f"value_channels[{i}]") for i, c in enumerate(value_channels))
            if len(chans) != self.num_levels or len(set(chans)) != 1:
                raise MSSFError(
                    f"value_channels: expected one channel count shared by all {self.num_levels} levels "
                    f"(FPN outputs; value_proj is shared across levels), got {chans}"
                )
            self.value_channels = chans[0]
        if method not in _METHODS:
            raise MSSFError(f"method: expected one of {_METHODS}, got {method!r}")
        self.method = method
        if value_projection not in _VALUE_PROJECTIONS:
            raise MSSFError(f"value_projection: expected one of {_VALUE_PROJECTIONS}, got {value_projection!r}")
        self.value_projection = value_projection
        factory = _factory(device, dtype)
        m, l, p = self.num_heads, self.num_levels, self.num_points
        self.sampling_offsets = nn.Linear(self.embed_dim, m * l * p * 2, **factory)
        self.attention_weights = nn.Linear(self.embed_dim, m * l * p, **factory)
        self.value_proj = nn.Linear(self.value_channels, self.embed_dim, **factory)
        self.output_proj = nn.Linear(self.embed_dim, self.embed_dim, **factory)
        self.norm = _norm(norm_layer, self.embed_dim, factory)
        self.reset_parameters()

    @property
    def head_dim(self) -> int:
        return self.embed_dim // self.num_heads

    def reset_parameters(self) -> None:
        """Deformable-DETR initialisation.

        Offsets start on a grid: head ``m`` points in direction ``2 pi m / M`` (scaled so the larger of
        ``|cos|, |sin|`` is 1), point ``p`` at distance ``p + 1`` pixels of every level; attention
        weights start uniform (zero weight and bias); projections are xavier-uniform with zero bias.
        """
        m, l, p = self.num_heads, self.num_levels, self.num_points
        nn.init.zeros_(self.sampling_offsets.weight)
        w = self.sampling_offsets.weight
        thetas = torch.arange(m, dtype=torch.float64) * (2.0 * math.pi / m)
        grid = torch.stack([thetas.cos(), thetas.sin()], dim=-1)
        grid = grid / grid.abs().max(dim=-1, keepdim=True).values
        grid = grid.view(m, 1, 1, 2).repeat(1, l, p, 1)
        grid = grid * torch.arange(1, p + 1, dtype=torch.float64).view(1, 1, p, 1)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(grid.reshape(-1).to(device=w.device, dtype=w.dtype))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        for lin in (self.value_proj, self.output_proj):
            nn.init.xavier_uniform_(lin.weight)
            nn.init.zeros_(lin.bias)

    def sampling_locations_and_weights(
        self, query: Tensor, uv: Tensor, level_sizes: Sequence[Tuple[int, int]]
    ) -> Tuple[Tensor, Tensor]:
        """Eq. 9 and the softmax: ``(Q, M, L, P, 2)`` locations and ``(Q, M, L, P)`` weights.

        Args:
            query: ``(Q, E)`` queries (one row per voxel-camera pair).
            uv: ``(Q, 2)`` normalised reference points.
            level_sizes: ``(H_l, W_l)`` of every level.
        """
        q = query.shape[0]
        m, l, p = self.num_heads, self.num_levels, self.num_points
        dtype = _sampling_dtype(self.value_proj.weight)
        with _autocast_off(query.device.type):  # locations in float32 at least (see the module doc)
            query = _to_sampling_dtype(query, dtype, "query", "MSDFF")
            uv = uv.to(dtype)
            aw, so = self.attention_weights, self.sampling_offsets
            weights = F.linear(query, aw.weight.to(dtype), aw.bias.to(dtype))
            weights = weights.view(q, m, l * p).softmax(dim=-1).view(q, m, l, p)
            # Offsets are in pixels of each level, location = uv + offset / (W_l, H_l). Both steps are
            # folded into one affine map of [query, uv]: the rows of sampling_offsets scaled by
            # (1 / W_l, 1 / H_l) plus a 0/1 selector that adds u (v) to every x (y) output. One GEMM
            # instead of a broadcast division and addition over the (Q, M, L, P, 2) output (measured
            # 4-6x faster on the CPU); equal up to float rounding.
            inv = torch.tensor([[1.0 / w, 1.0 / h] for h, w in level_sizes], dtype=dtype, device=query.device)
            scale = inv.view(1, l, 1, 2).expand(m, l, p, 2).reshape(-1, 1)  # (M * L * P * 2, 1)
            select = torch.eye(2, dtype=dtype, device=query.device).repeat(m * l * p, 1)  # (M * L * P * 2, 2)
            weight = torch.cat([so.weight.to(dtype) * scale, select], 1)
            locations = torch.addmm(so.bias.to(dtype) * scale[:, 0], torch.cat([query, uv], 1), weight.t())
        return locations.view(q, m, l, p, 2), weights

    def forward(
        self, query: Tensor, image_features: Sequence[Tensor], projection: CentroidProjection
    ) -> Tensor:
        levels = check_image_features(
            image_features, num_levels=self.num_levels, channels=[self.value_channels] * self.num_levels
        )
        b, v = levels[0].shape[:2]
        uv, valid, batch_index = _check_projection(projection, b, v)
        n = uv.shape[0]
        check_shape(query, "query", (n, self.embed_dim))
        check_floating(query, "query")
        m, e, c = self.num_heads, self.embed_dim, self.value_channels

        # The sampling runs in float32 (float64 for a float64 module), autocast or not: lower-precision
        # levels are read as float32 and the locations are never rounded to half precision.
        dtype = _sampling_dtype(self.value_proj.weight)
        levels = [_to_sampling_dtype(lvl, dtype, f"image_features[{i}]", "MSDFF") for i, lvl in enumerate(levels)]
        uv = uv.to(dtype)
        with _autocast_off(uv.device.type):
            # One attention query per (voxel, camera) pair where the voxel is valid; offsets and weights
            # depend on the query only, so they are computed per voxel and gathered.
            sizes = [tuple(lvl.shape[-2:]) for lvl in levels]
            one_each = v == 1 and bool(valid.all())
            if one_each:  # one camera that sees every voxel (the usual case): no gathers or scatters
                locations, weights = self.sampling_locations_and_weights(query, uv[:, 0], sizes)
                image_index = batch_index
            else:
                n_idx, v_idx = valid.nonzero(as_tuple=True)
                locations, weights = self.sampling_locations_and_weights(query, uv.new_zeros(n, 2), sizes)
                locations = locations[n_idx] + uv[n_idx, v_idx][:, None, None, None, :]
                weights = weights[n_idx]
                image_index = batch_index[n_idx] * v + v_idx
            w_heads = self.value_proj.weight.to(dtype).view(m, self.head_dim, c)
            b_heads = self.value_proj.bias.to(dtype).view(m, self.head_dim)
            raw = [lvl.reshape(b * v, 1, c, lvl.shape[-2], lvl.shape[-1]) for lvl in levels]  # Mv = 1 views
            if self.method == "auto":
                # Either order, restricted to the pixels some bilinear corner reads: per level the cheapest
                # of project-all / project-touched / sample-touched-then-project (exact, bias included).
                heads = ms_deform_sample_project(raw, image_index, locations, weights, w_heads, b_heads,
                                                 method="touched")
            elif self.value_projection == "after_sampling":
                sampled, mass = ms_deform_sample(
                    raw, image_index, locations, weights, method=self.method, return_mass=True
                )  # (Q, M, C), (Q, M)
                # value_proj after sampling: head m uses rows [m*d, (m+1)*d) of the projection; its bias
                # contributes only where the bilinear corners were inside the image (zero padding).
                heads = torch.einsum("qmc,mdc->qmd", sampled, w_heads) + mass[..., None] * b_heads
            else:
                values = []
                for lvl in levels:
                    h, w = lvl.shape[-2:]
                    projected = F.linear(lvl.reshape(b * v, c, h, w).permute(0, 2, 3, 1), w_heads.reshape(e, c),
                                         b_heads.reshape(e))  # (I, H, W, E)
                    values.append(projected.view(b * v, h, w, m, self.head_dim).permute(0, 3, 4, 1, 2))
                heads = ms_deform_sample(values, image_index, locations, weights, method=self.method)
            if one_each:
                attended = heads.reshape(n, e)
            else:
                per_camera = heads.new_zeros(n, v, e).index_put((n_idx, v_idx), heads.reshape(-1, e))
                attended = camera_mean(per_camera, valid)
        attended = attended.to(self.output_proj.weight.dtype)
        return _linear_bn_visible(self.output_proj, self.norm, attended, valid.any(dim=1))

    def extra_repr(self) -> str:
        return (
            f"embed_dim={self.embed_dim}, value_channels={self.value_channels}, num_heads={self.num_heads}, "
            f"num_levels={self.num_levels}, num_points={self.num_points}, method={self.method!r}, "
            f"value_projection={self.value_projection!r}"
        )


# ---------------------------------------------------------------------------------------------------
# QueryInit
# ---------------------------------------------------------------------------------------------------
class QueryInit(nn.Module):
    """MSDFF query initialisation (paper eq. 8): ``Linear_BN(cat(f_vox, f_img^1, p))``.

    Args:
        voxel_channels: ``C_v`` of ``f_vox``.
        image_channels: ``C_i`` of ``f_img^1`` (the first image level sampled at the centroid).
        out_channels: query channels (the MSDFF ``embed_dim``).
        point_cloud_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` used to normalise voxel
            centres to ``p`` in ``[0, 1]^3``.
        norm_layer: normalisation after the linear layer.
        device, dtype: factory arguments of the parameters.

    Shapes:
        - f_vox ``(N, C_v)``, f_img0 ``(N, C_i)``, centers ``(N, 3)`` metric ``(x, y, z)``.
        - output ``(N, out_channels)``.
    """

    def __init__(
        self,
        voxel_channels: int,
        image_channels: int,
        out_channels: int,
        point_cloud_range: Sequence[float],
        norm_layer: Type[nn.Module] = nn.BatchNorm1d,
        device=None,
        dtype=None,
    ) -> None:
        super().__init__()
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
        check_shape(f_vox, "f_vox", ("N", self.voxel_channels), dims)
        check_shape(f_img0, "f_img0", ("N", self.image_channels), dims)
        check_shape(centers, "centers", ("N", 3), dims)
        for x, name in ((f_vox, "f_vox"), (f_img0, "f_img0"), (centers, "centers")):
            check_floating(x, name)
        p = self.normalized_centers(centers.to(f_vox.dtype))
        return self.norm(self.linear(torch.cat([f_vox, f_img0.to(f_vox.dtype), p], dim=1)))

    def extra_repr(self) -> str:
        return (
            f"voxel_channels={self.voxel_channels}, image_channels={self.image_channels}, "
            f"out_channels={self.out_channels}, point_cloud_range={self.point_cloud_range}"
        )
