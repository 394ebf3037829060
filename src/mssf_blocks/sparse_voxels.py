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

from mssf_blocks.checks.arguments import check_positive_int, check_triple
from mssf_blocks.checks.tensors import check_voxel_features, check_voxel_tensors
from mssf_blocks.errors import MSSFError
from mssf_blocks.voxel_grid import VoxelGrid
from mssf_blocks.static_path import register_pytree

__all__ = ["SparseVoxels"]


@dataclass(frozen=True, eq=False, init=False)
class SparseVoxels:
    """Non-empty voxels of a batch of scenes.

    Attributes:
        features: ``(N, C)`` floating-point voxel features.
        coords: ``(N, 4)`` int32 ``(batch, z, y, x)`` indices at this tensor's stride. Rows need not be
            grouped or sorted by batch.
        spatial_shape: ``(D, H, W)`` grid size at this tensor's stride (``z, y, x``); default: the grid's
            at ``stride``.
        batch_size: number of samples ``B``; every batch index is ``< B``.
        grid: the :class:`~mssf_blocks.geometry.VoxelGrid` (``voxel_size`` + ``point_cloud_range``, x, y, z).
        stride: ``(sz, sy, sx)`` of this tensor relative to the grid; default: read from ``spatial_shape``
            against the grid (:meth:`VoxelGrid.stride_of`), ``(1, 1, 1)`` without a ``spatial_shape``.

    ``voxel_size=`` and ``point_range_min=`` (keywords, both ``(x, y, z)``) are the loose spelling of the
    grid: the grid is then the range the tensor spans (:meth:`VoxelGrid.covering`), at ``stride``
    (default ``(1, 1, 1)``). Read back as ``.voxel_size`` / ``.point_range_min`` either way.

    The metric centre of voxel ``(b, z, y, x)`` is
    ``(index + 0.5) * voxel_size * stride + point_range_min`` per axis (see :meth:`voxel_centers`).

    Example:
        >>> import torch
        >>> from mssf_blocks import VoxelGrid
        >>> grid = VoxelGrid(voxel_size=(0.1, 0.1, 0.2), point_cloud_range=(0.0, -0.4, -0.4, 0.8, 0.4, 0.4))
        >>> v = SparseVoxels(torch.ones(2, 4), torch.tensor([[0, 0, 1, 2], [1, 3, 0, 0]], dtype=torch.int32),
        ...                  batch_size=2, grid=grid)
        >>> v.spatial_shape, v.stride
        ((4, 8, 8), (1, 1, 1))
        >>> v.voxel_centers()
        tensor([[ 0.2500, -0.2500, -0.3000],
                [ 0.0500, -0.3500,  0.3000]])
    """

    features: Tensor
    coords: Tensor
    spatial_shape: Tuple[int, int, int]
    batch_size: int
    grid: VoxelGrid
    stride: Tuple[int, int, int] = (1, 1, 1)
    # The spconv tensor this was made from (keeps its index cache); dropped when coords change.
    spconv_source: Optional[Any] = field(default=None, repr=False)

    def __init__(self, features: Tensor, coords: Tensor, spatial_shape: Optional[Sequence[int]] = None,
                 batch_size: Optional[int] = None, grid: Optional[VoxelGrid] = None,
                 stride: Optional[Sequence[int]] = None, spconv_source: Optional[Any] = None, *,
                 voxel_size: Optional[Sequence[float]] = None,
                 point_range_min: Optional[Sequence[float]] = None) -> None:
        set_ = object.__setattr__
        if batch_size is None:
            raise MSSFError("batch_size: expected a positive int (the number of samples B), got None")
        loose = voxel_size is not None or point_range_min is not None
        if grid is not None and not isinstance(grid, VoxelGrid):
            raise MSSFError(
                f"grid: expected a VoxelGrid, got {type(grid).__name__} ({grid!r}); pass grid=VoxelGrid(voxel_size, "
                "point_cloud_range), or the loose form voxel_size=..., point_range_min=... as keywords")
        if grid is not None and loose:
            raise MSSFError("grid: expected either grid= or voxel_size= with point_range_min=, got both")
        if grid is None and not (voxel_size is not None and point_range_min is not None):
            raise MSSFError("grid: expected a VoxelGrid (or voxel_size= and point_range_min=), got "
                            + ("only one of voxel_size / point_range_min" if loose else "none"))
        if spatial_shape is None and grid is None:
            raise MSSFError("spatial_shape: expected (D, H, W) ints with the loose voxel_size / point_range_min "
                            "form, got None")
        if stride is not None:
            stride = check_triple(stride, "stride", int, positive=True)
        if spatial_shape is None:
            stride = stride or (1, 1, 1)
            base = grid.spatial_shape
            spatial_shape = tuple(-(-n // s) for n, s in zip(base, stride))
        spatial_shape = check_triple(spatial_shape, "spatial_shape", int, positive=True)
        if grid is None:
            stride = stride or (1, 1, 1)
            grid = VoxelGrid.covering(check_triple(voxel_size, "voxel_size", float, positive=True),
                                      check_triple(point_range_min, "point_range_min", float), spatial_shape, stride)
        elif stride is None:
            stride = grid.stride_of(spatial_shape, "spatial_shape")
        set_(self, "features", features)
        set_(self, "coords", coords)
        set_(self, "spatial_shape", spatial_shape)
        set_(self, "batch_size", check_positive_int(batch_size, "batch_size"))
        set_(self, "grid", grid)
        # (plain attributes, not properties: read on every block's path, and the grid is immutable)
        set_(self, "voxel_size", grid.voxel_size)  # (x, y, z) metres of one voxel at stride 1
        set_(self, "point_range_min", grid.point_range_min)  # (x, y, z) lower corner
        set_(self, "stride", stride)
        set_(self, "spconv_source", spconv_source)
        check_voxel_tensors(self.features, self.coords, self.spatial_shape, self.batch_size)

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
        from mssf_blocks.functional.geometry import voxel_centers

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
        # (the loose spelling of the grid, as in the constructor)
        loose = {k: changes.pop(k) for k in ("voxel_size", "point_range_min") if k in changes}
        unknown = set(changes) - set(self.__dataclass_fields__)
        if unknown:
            raise MSSFError(
                f"replace: unknown field(s) {sorted(unknown)}; expected some of "
                f"{sorted(self.__dataclass_fields__)}"
            )
        if set(changes) <= {"features"} and not loose:
            new = object.__new__(type(self))
            new.__dict__.update(self.__dict__)
            object.__setattr__(new, "features", changes.get("features", self.features))
            check_voxel_features(new.features, self.num_voxels)
            return new
        kwargs = {name: getattr(self, name) for name in self.__dataclass_fields__}
        if any(k in changes for k in ("coords", "spatial_shape", "batch_size", "grid", "stride")) or loose:
            kwargs["spconv_source"] = None
        kwargs.update(changes)
        if loose:
            del kwargs["grid"]
            kwargs["voxel_size"] = loose.get("voxel_size", self.voxel_size)
            kwargs["point_range_min"] = loose.get("point_range_min", self.point_range_min)
        return type(self)(**kwargs)

    def to(self, *args: Any, **kwargs: Any) -> "SparseVoxels":
        """Move features (and coords, for device moves) like :meth:`torch.Tensor.to`."""
        features = self.features.to(*args, **kwargs)
        coords = self.coords.to(device=features.device)
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
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
        grid: Optional[VoxelGrid] = None,
        stride: Optional[Sequence[int]] = None,
        *,
        voxel_size: Optional[Sequence[float]] = None,
        point_range_min: Optional[Sequence[float]] = None,
    ) -> "SparseVoxels":
        """Wrap an spconv ``SparseConvTensor`` (its features, indices and index cache are shared).

        Args:
            tensor: ``spconv.pytorch.SparseConvTensor`` with 3D ``spatial_shape``.
            grid: the :class:`~mssf_blocks.geometry.VoxelGrid` of its voxels (or the loose keywords
                ``voxel_size=`` and ``point_range_min=``, as in the constructor).
            stride: ``(sz, sy, sx)`` of ``tensor`` relative to the grid; default: read from its
                ``spatial_shape`` against the grid.
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
            grid=grid,
            stride=stride,
            spconv_source=tensor,
            voxel_size=voxel_size,
            point_range_min=point_range_min,
        )

    def to_spconv(self) -> Any:
        """An spconv ``SparseConvTensor`` with these features.

        If this object came from :meth:`from_spconv` and its voxel set is unchanged, the result keeps
        the source's index cache (``indice_dict``, grid, benchmark settings), so later ``SubMConv3d`` /
        inverse convs with the same ``indice_key`` still find their indices.
        """
        from mssf_blocks.checks.spconv_inputs import check_spconv_input  # (quiet: spconv's own torch.fx message)
        from mssf_blocks.integrations.spconv import quiet

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


# torch.export / ONNX: features and coords are graph inputs; the rest is the graph's fixed context
register_pytree(SparseVoxels, ("features", "coords"), ("spatial_shape", "batch_size", "grid", "stride"))
