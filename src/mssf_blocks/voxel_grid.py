"""``VoxelGrid``: the one description of a model's voxel grid, ``voxel_size`` + ``point_cloud_range``.

mmdetection3d and OpenPCDet keep one ``voxel_size`` (x, y, z) and one 6-value ``point_cloud_range``
``(x_min, y_min, z_min, x_max, y_max, z_max)`` per model and hand them to every module; so does this
library: every block that needs metres takes a grid (``FusionBlock``, ``QueryInit``, the projector,
``PillarLift``, ``SparseVoxels``). A sparse tensor at some stride of the grid has a ``spatial_shape``
``(D, H, W)`` = (z, y, x) cells; :meth:`VoxelGrid.stride_of` reads its stride from that shape, so no
block asks for it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.arguments import check_point_cloud_range, check_triple
from mssf_blocks.errors import MSSFError

__all__ = ["VoxelGrid"]

#: the largest power-of-two stride tried per axis (2 ** 7 = 128: beyond any backbone's downsampling)
_MAX_LOG2_STRIDE = 7


def _reachable(cells: int, log2_stride: int) -> set:
    """Axis sizes a ``cells``-cell axis can have after ``log2_stride`` stride-2 convolutions: each one maps
    ``m`` to ``ceil(m / 2)`` (kernel 3, padding 1), ``floor((m - 1) / 2)`` (kernel 3, padding 0) or
    ``floor(m / 2)`` (kernel 2); the input is ``cells`` or ``cells + 1`` (OpenPCDet and mmdetection3d give
    their sparse tensors one z cell more than the grid: ``sparse_shape = grid_size[::-1] + [1, 0, 0]``)."""
    sizes = {cells, cells + 1}
    for _ in range(log2_stride):
        sizes = {s for m in sizes for s in (-(-m // 2), (m - 1) // 2, m // 2) if s >= 1}
    return sizes


@dataclass(frozen=True)
class VoxelGrid:
    """A voxel grid in metres: ``voxel_size (x, y, z)`` and ``point_cloud_range (x_min, y_min, z_min,
    x_max, y_max, z_max)``, as mmdetection3d and OpenPCDet configs write them.

    Args:
        voxel_size: ``(x, y, z)`` metres of one voxel of the base grid (stride 1).
        point_cloud_range: the 6 values; each axis must hold a whole number of voxels within 1e-3 of one
            (the frameworks round ``(max - min) / voxel_size`` to the grid size).

    Example:
        >>> grid = VoxelGrid(voxel_size=(0.05, 0.05, 0.125), point_cloud_range=(0, -25.6, -3, 51.2, 25.6, 2))
        >>> grid.spatial_shape  # (D, H, W) = (z, y, x) cells at stride 1
        (40, 1024, 1024)
        >>> grid.stride_of((21, 512, 512))  # an spconv tensor after one stride-2 stage (OpenPCDet's 41 z cells)
        (2, 2, 2)
    """

    voxel_size: Tuple[float, float, float]
    point_cloud_range: Tuple[float, float, float, float, float, float]

    def __post_init__(self) -> None:
        vs = check_triple(self.voxel_size, "voxel_size", float)
        if not all(v > 0 for v in vs):
            raise MSSFError(f"voxel_size: expected 3 positive numbers (x, y, z) in metres, got {self.voxel_size!r}")
        pcr = check_point_cloud_range(self.point_cloud_range)
        for a, axis in enumerate("xyz"):
            cells = (pcr[a + 3] - pcr[a]) / vs[a]
            if abs(cells - round(cells)) > 1e-3 * max(1.0, cells) or round(cells) < 1:
                raise MSSFError(
                    f"point_cloud_range: expected a whole number of voxels along {axis}, got "
                    f"({pcr[a + 3]} - {pcr[a]}) / voxel_size {vs[a]} = {cells:.4f} cells (not a multiple of "
                    "voxel_size); adjust the range or voxel_size (the frameworks round this to the grid size)"
                )
        object.__setattr__(self, "voxel_size", vs)
        object.__setattr__(self, "point_cloud_range", pcr)

    # -- alternative spelling ---------------------------------------------------------------------
    @classmethod
    def covering(cls, voxel_size: Sequence[float], point_range_min: Sequence[float],
                 spatial_shape: Sequence[int], stride: Sequence[int] = (1, 1, 1)) -> "VoxelGrid":
        """The grid a sparse tensor spans: ``point_range_min`` up to ``min + spatial_shape * stride *
        voxel_size`` (the loose ``voxel_size=`` / ``point_range_min=`` spelling of a grid)."""
        vs = check_triple(voxel_size, "voxel_size", float)
        lo = check_triple(point_range_min, "point_range_min", float)
        d, h, w = (int(s) for s in spatial_shape)
        sz, sy, sx = (int(s) for s in stride)
        hi = (lo[0] + w * sx * vs[0], lo[1] + h * sy * vs[1], lo[2] + d * sz * vs[2])
        return cls(vs, lo + hi)

    # -- derived ----------------------------------------------------------------------------------
    @property
    def point_range_min(self) -> Tuple[float, float, float]:
        """``(x, y, z)`` lower corner in metres."""
        return self.point_cloud_range[:3]  # type: ignore[return-value]

    @property
    def point_range_max(self) -> Tuple[float, float, float]:
        """``(x, y, z)`` upper corner in metres."""
        return self.point_cloud_range[3:]  # type: ignore[return-value]

    @property
    def grid_size(self) -> Tuple[int, int, int]:
        """``(nx, ny, nz)`` cells at stride 1 (mmdetection3d's and OpenPCDet's ``grid_size``, x first)."""
        d, h, w = self.spatial_shape
        return (w, h, d)

    @property
    def spatial_shape(self) -> Tuple[int, int, int]:
        """``(D, H, W)`` = (z, y, x) cells at stride 1."""
        cells = [round((self.point_cloud_range[a + 3] - self.point_cloud_range[a]) / self.voxel_size[a])
                 for a in range(3)]
        return (int(cells[2]), int(cells[1]), int(cells[0]))

    def stride_of(self, spatial_shape: Sequence[Any], name: str = "x.spatial_shape") -> Tuple[int, int, int]:
        """``(sz, sy, sx)`` of a sparse tensor of this grid whose shape is ``spatial_shape`` ``(D, H, W)``.

        Per axis, the power-of-two strides whose stride-2 convolutions (kernel 3 with padding 1 or 0, or
        kernel 2) can turn the grid's cells (or one more: OpenPCDet's extra z cell) into that size. An
        axis that fits several (a coarse z axis: 2 cells fit strides 16 and 32 of a 40-cell axis) takes the
        stride the other axes agree on when it is among its own; otherwise, or when an axis fits none, the
        shape is refused with both shapes named (build the tensor as ``SparseVoxels(..., stride=...)``).
        """
        try:
            shape = tuple(int(s) for s in spatial_shape)
        except (TypeError, ValueError):
            raise MSSFError(f"{name}: expected 3 ints (D, H, W), got {spatial_shape!r}") from None
        if len(shape) != 3:
            raise MSSFError(f"{name}: expected 3 ints (D, H, W), got {spatial_shape!r}")
        base = self.spatial_shape
        candidates: List[List[int]] = [
            [2 ** k for k in range(_MAX_LOG2_STRIDE + 1) if m in _reachable(n, k)] for n, m in zip(base, shape)
        ]
        sure = {c[0] for c in candidates if len(c) == 1}
        agreed: Optional[int] = next(iter(sure)) if len(sure) == 1 else None
        stride = []
        for a, (c, axis) in enumerate(zip(candidates, "zyx")):
            if len(c) == 1:
                stride.append(c[0])
            elif agreed is not None and agreed in c:
                stride.append(agreed)
            else:
                what = (f"no power-of-two stride of the grid's {base[a]} {axis} cells gives {shape[a]}" if not c
                        else f"the {axis} axis fits strides {c} and the other axes do not decide")
                perm = self._permutation_that_fits(shape)
                if perm is not None:
                    what += f"; {perm} would fit: spatial_shape is (D, H, W) = (z, y, x) cells, given in another order?"
                raise MSSFError(
                    f"{name}: expected the shape of a sparse tensor on the grid (its (D, H, W) = {base} at stride 1, "
                    f"over a whole power-of-two stride per axis), got {shape}: {what}. Check voxel_size (x, y, z "
                    "order) and point_cloud_range against the voxels' grid, or wrap the tensor as "
                    "SparseVoxels(..., grid=grid, stride=(sz, sy, sx)) to state its stride"
                )
        return (stride[0], stride[1], stride[2])

    def _permutation_that_fits(self, shape: Tuple[int, int, int]) -> Optional[Tuple[int, int, int]]:
        import itertools

        for perm in itertools.permutations(shape):
            if perm != shape and all(any(m in _reachable(n, k) for k in range(_MAX_LOG2_STRIDE + 1))
                                     for n, m in zip(self.spatial_shape, perm)):
                return perm
        return None

    def voxel_centers(self, coords: Tensor, stride: Sequence[int] = (1, 1, 1),
                      dtype: torch.dtype = torch.float32) -> Tensor:
        """``(N, 3)`` metric ``(x, y, z)`` centres of ``coords (N, 4)`` ``(batch, z, y, x)`` at ``stride``:
        ``(index + 0.5) * voxel_size * stride + point_range_min``."""
        from mssf_blocks.functional.geometry import voxel_centers

        return voxel_centers(coords, self.voxel_size, self.point_range_min, tuple(stride), dtype=dtype)

    def __repr__(self) -> str:
        return f"VoxelGrid(voxel_size={self.voxel_size}, point_cloud_range={self.point_cloud_range})"
