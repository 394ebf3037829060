"""``SparseVoxels``: the minimal sparse-voxel tensor every block works on.

It holds exactly what a fusion block needs besides features: which voxel each row is (``coords`` in
spconv/OpenPCDet order ``(batch, z, y, x)``) and where that voxel is in metres (base voxel size, range
minimum and the stride of this tensor relative to the base grid). It converts losslessly to and from
an spconv ``SparseConvTensor`` without importing spconv at module level.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional, Sequence, Tuple

import torch
from torch import Tensor

from ._checks import (
    check_dtype,
    check_floating,
    check_index_ranges,
    check_positive_int,
    check_shape,
    check_triple,
)
from .errors import MSSFError

__all__ = ["SparseVoxels"]


def _permutation_hint(coords: Tensor, spatial_shape: Tuple[int, int, int]) -> str:
    """Where the coordinates fit a permutation of ``spatial_shape`` (e.g. ``(W, H, D)`` given), say so."""
    import itertools

    if int(coords[:, 1:].amin()) < 0:
        return ""
    top = [int(v) + 1 for v in coords[:, 1:].amax(0).tolist()]  # (z, y, x) extents needed
    candidates = [tuple(spatial_shape)[::-1]] + list(itertools.permutations(spatial_shape))  # (W, H, D) first
    fits = [p for p in candidates
            if p != tuple(spatial_shape) and all(t <= s for t, s in zip(top, p))]
    if not fits:
        return ""
    return (f"; the coordinates fit spatial_shape={fits[0]}: spatial_shape is (D, H, W) = (z, y, x) cells, "
            f"given in another axis order (e.g. (W, H, D))?")


@dataclass(frozen=True, eq=False)
class SparseVoxels:
    """Non-empty voxels of a batch of scenes.

    Attributes:
        features: ``(N, C)`` floating-point voxel features.
        coords: ``(N, 4)`` int32 ``(batch, z, y, x)`` indices at this tensor's stride. Rows need not be
            grouped or sorted by batch.
        spatial_shape: ``(D, H, W)`` grid size at this tensor's stride (``z, y, x``).
        batch_size: number of samples ``B``; every batch index is ``< B``.
        voxel_size: ``(x, y, z)`` metres of one voxel of the *base* grid (stride 1).
        point_range_min: ``(x, y, z)`` metres of the grid's lower corner.
        stride: ``(sz, sy, sx)`` of this tensor relative to the base grid.

    The metric centre of voxel ``(b, z, y, x)`` is
    ``(index + 0.5) * voxel_size * stride + point_range_min`` per axis (see :meth:`voxel_centers`).

    Example:
        >>> import torch
        >>> v = SparseVoxels(
        ...     features=torch.ones(2, 4),
        ...     coords=torch.tensor([[0, 0, 1, 2], [1, 3, 0, 0]], dtype=torch.int32),
        ...     spatial_shape=(4, 8, 8), batch_size=2,
        ...     voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, -0.4, -0.4))
        >>> v.voxel_centers()
        tensor([[ 0.2500, -0.2500, -0.3000],
                [ 0.0500, -0.3500,  0.3000]])
    """

    features: Tensor
    coords: Tensor
    spatial_shape: Tuple[int, int, int]
    batch_size: int
    voxel_size: Tuple[float, float, float]
    point_range_min: Tuple[float, float, float]
    stride: Tuple[int, int, int] = (1, 1, 1)
    # The spconv tensor this was made from (keeps its index cache); dropped when coords change.
    spconv_source: Optional[Any] = field(default=None, repr=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "spatial_shape", check_triple(self.spatial_shape, "spatial_shape", int, positive=True))
        set_(self, "batch_size", check_positive_int(self.batch_size, "batch_size"))
        set_(self, "voxel_size", check_triple(self.voxel_size, "voxel_size", float, positive=True))
        set_(self, "point_range_min", check_triple(self.point_range_min, "point_range_min", float))
        set_(self, "stride", check_triple(self.stride, "stride", int, positive=True))
        self._check_coords(self.coords)
        self._check_features(self.features, self.coords.shape[0])

    # -- validation -------------------------------------------------------------------------------
    def _check_coords(self, coords: Tensor) -> None:
        check_shape(coords, "coords", ("N", 4))
        check_dtype(coords, "coords", (torch.int32,), hint=" (convert with coords.int())")
        if coords.numel():
            # one host synchronisation for the four range checks, not eight (a GPU stalls on each)
            try:
                check_index_ranges(
                    [(coords[:, 0], "coords[:, 0] (batch index)", self.batch_size, "batch_size")]
                    + [(coords[:, a], f"coords[:, {a}] ({n} index)", self.spatial_shape[a - 1],
                        f"spatial_shape[{a - 1}]") for a, n in zip((1, 2, 3), ("z", "y", "x"))]
                )
            except MSSFError as exc:  # (the error path only: one more read, to name a permuted spatial_shape)
                raise MSSFError(f"{exc}{_permutation_hint(coords, self.spatial_shape)}") from None

    @staticmethod
    def _check_features(features: Tensor, n: int) -> None:
        check_shape(features, "features", (n, None))
        check_floating(features, "features")

    # -- derived ----------------------------------------------------------------------------------
    @property
    def num_voxels(self) -> int:
        # (the size itself, not int(): a symbolic size under torch.compile / export stays symbolic)
        return self.coords.shape[0]

    @property
    def num_channels(self) -> int:
        return self.features.shape[1]

    @property
    def batch_index(self) -> Tensor:
        """``(N,)`` int64 batch index of every row."""
        return self.coords[:, 0].long()

    @property
    def metric_voxel_size(self) -> Tuple[float, float, float]:
        """``(x, y, z)`` metres of one voxel at this tensor's stride."""
        sz, sy, sx = self.stride
        vx, vy, vz = self.voxel_size
        return (vx * sx, vy * sy, vz * sz)

    @property
    def point_range_max(self) -> Tuple[float, float, float]:
        """``(x, y, z)`` upper corner covered by this grid (``min + shape * stride * voxel_size``)."""
        d, h, w = self.spatial_shape
        mx, my, mz = self.metric_voxel_size
        x0, y0, z0 = self.point_range_min
        return (x0 + w * mx, y0 + h * my, z0 + d * mz)

    def voxel_centers(self, dtype: Optional[torch.dtype] = None) -> Tensor:
        """``(N, 3)`` metric ``(x, y, z)`` centre of every voxel."""
        from .functional.geometry import voxel_centers

        return voxel_centers(
            self.coords, self.voxel_size, self.point_range_min, self.stride,
            dtype=dtype or (self.features.dtype if self.features.is_floating_point() else torch.float32),
        )

    # -- functional updates -----------------------------------------------------------------------
    def replace(self, **changes: Any) -> "SparseVoxels":
        """A new ``SparseVoxels`` with some fields changed.

        Changing only ``features`` (the common case inside a block) checks just their shape and keeps
        the spconv index cache; changing ``coords`` or the grid drops the cache and re-validates.
        """
        unknown = set(changes) - set(self.__dataclass_fields__)
        if unknown:
            raise MSSFError(
                f"replace: unknown field(s) {sorted(unknown)}; expected some of "
                f"{sorted(self.__dataclass_fields__)}"
            )
        if set(changes) <= {"features"}:
            new = object.__new__(type(self))
            for name in self.__dataclass_fields__:
                object.__setattr__(new, name, changes.get(name, getattr(self, name)))
            self._check_features(new.features, self.num_voxels)
            return new
        kwargs = {name: getattr(self, name) for name in self.__dataclass_fields__}
        if any(k in changes for k in ("coords", "spatial_shape", "batch_size")):
            kwargs["spconv_source"] = None
        kwargs.update(changes)
        return type(self)(**kwargs)

    def to(self, *args: Any, **kwargs: Any) -> "SparseVoxels":
        """Move features (and coords, for device moves) like :meth:`torch.Tensor.to`."""
        features = self.features.to(*args, **kwargs)
        coords = self.coords.to(device=features.device)
        new = object.__new__(type(self))
        for name in self.__dataclass_fields__:
            object.__setattr__(new, name, getattr(self, name))
        object.__setattr__(new, "features", features)
        object.__setattr__(new, "coords", coords)
        if coords.device != self.coords.device:
            object.__setattr__(new, "spconv_source", None)
        return new

    # -- spconv interop ---------------------------------------------------------------------------
    @classmethod
    def from_spconv(
        cls,
        tensor: Any,
        voxel_size: Sequence[float],
        point_range_min: Sequence[float],
        stride: Sequence[int] = (1, 1, 1),
    ) -> "SparseVoxels":
        """Wrap an spconv ``SparseConvTensor`` (its features, indices and index cache are shared).

        Args:
            tensor: ``spconv.pytorch.SparseConvTensor`` with 3D ``spatial_shape``.
            voxel_size: base-grid ``(x, y, z)`` voxel size in metres.
            point_range_min: ``(x, y, z)`` lower corner in metres.
            stride: ``(sz, sy, sx)`` of ``tensor`` relative to the base grid.
        """
        for attr in ("features", "indices", "spatial_shape", "batch_size"):
            if not hasattr(tensor, attr):
                raise MSSFError(
                    f"tensor: expected an spconv SparseConvTensor (with .{attr}), got {type(tensor).__name__}"
                )
        return cls(
            features=tensor.features,
            coords=tensor.indices,
            spatial_shape=tuple(int(s) for s in tensor.spatial_shape),
            batch_size=int(tensor.batch_size),
            voxel_size=voxel_size,
            point_range_min=point_range_min,
            stride=stride,
            spconv_source=tensor,
        )

    def to_spconv(self) -> Any:
        """An spconv ``SparseConvTensor`` with these features.

        If this object came from :meth:`from_spconv` and its voxel set is unchanged, the result keeps
        the source's index cache (``indice_dict``, grid, benchmark settings), so later ``SubMConv3d`` /
        inverse convs with the same ``indice_key`` still find their indices.
        """
        from .compat.spconv import check_spconv_input, quiet  # (quiet: spconv's own torch.fx message)

        check_spconv_input(self.features, self.coords, self.spatial_shape, self.batch_size)

        if self.spconv_source is not None:
            with quiet():
                return self.spconv_source.replace_feature(self.features)
        try:
            import spconv.pytorch as spconv
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError(
                "SparseVoxels.to_spconv needs spconv: pip install 'mssf-blocks[spconv]'"
            ) from exc
        with quiet():
            return spconv.SparseConvTensor(
                self.features, self.coords, list(self.spatial_shape), self.batch_size
            )

    def __repr__(self) -> str:
        return (
            f"SparseVoxels(num_voxels={self.num_voxels}, channels={self.num_channels}, "
            f"spatial_shape={self.spatial_shape}, batch_size={self.batch_size}, stride={self.stride}, "
            f"voxel_size={self.voxel_size}, point_range_min={self.point_range_min}, "
            f"dtype={self.features.dtype}, device={self.features.device})"
        )
