"""``VoxelCentroidProjector``: voxel centroids of a sparse tensor, projected into the cameras.

This is the first half of every MSSF fusion block (paper Sec. III-C, eq. 1-2): find the centroid of
the raw points inside each non-empty voxel (its centre if it holds none), then project it with the
camera matrices to normalised image coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import Tensor, nn

from ._checks import check_points, check_shape, check_triple
from .errors import MSSFError
from .functional.geometry import project_points, voxel_centroids
from .sparse import SparseVoxels

__all__ = ["VoxelCentroidProjector", "CentroidProjection", "augmentation_matrix"]


@dataclass(frozen=True)
class CentroidProjection:
    """What a fusion block needs to sample the image for every voxel.

    Attributes:
        uv: ``(N, V, 2)`` normalised sampling coordinates ``((u + 0.5) / W, (v + 0.5) / H)``.
        depth: ``(N, V)`` camera depth.
        valid: ``(N, V)`` depth above ``eps`` and inside the image.
        centroid: ``(N, 3)`` metric ``(x, y, z)`` centroid (centre where the voxel holds no point).
        has_points: ``(N,)`` which voxels hold raw points.
        batch_index: ``(N,)`` int64 batch index of every voxel.
    """

    uv: Tensor
    depth: Tensor
    valid: Tensor
    centroid: Tensor
    has_points: Tensor
    batch_index: Tensor

    @property
    def num_cameras(self) -> int:
        return int(self.uv.shape[1])


class VoxelCentroidProjector(nn.Module):
    """Centroids of a :class:`SparseVoxels` projected into ``V`` cameras.

    Args:
        eps: depths ``<= eps`` are invalid (behind the camera).
        point_range_max: optional ``(x, y, z)`` upper corner of the point-cloud range; points at or
            above it are ignored (by default, points beyond the grid are ignored).

    Shapes:
        - voxels: N voxels at any stride; points ``(P, 3)`` x, y, z (slice other columns off: extra
          columns are refused); points_batch ``(P,)``.
        - lidar2img ``(B, V, 3, 4)`` or ``(B, 3, 4)``; points_to_sensor ``(B, 4, 4)``.
        - output: :class:`CentroidProjection` with ``uv (N, V, 2)``, ``depth (N, V)``, ``valid (N, V)``,
          ``centroid (N, 3)``, ``has_points (N,)``, in the dtype of ``points`` (float32 for float16 /
          bfloat16 points: half-precision centroids would be off by decimetres).

    Example:
        >>> import torch
        >>> from mssf_blocks import SparseVoxels, VoxelCentroidProjector
        >>> vox = SparseVoxels(torch.zeros(1, 2), torch.tensor([[0, 0, 0, 0]], dtype=torch.int32),
        ...                    (1, 1, 1), 1, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
        >>> pts = torch.tensor([[0.25, 0.5, 0.75]])
        >>> l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]])  # depth 1, u = x, v = y
        >>> out = VoxelCentroidProjector()(vox, pts, torch.zeros(1, dtype=torch.long), l2i, (4, 4))
        >>> out.centroid, out.uv
        (tensor([[0.2500, 0.5000, 0.7500]]), tensor([[[0.1875, 0.2500]]]))
    """

    def __init__(self, eps: float = 1e-5, point_range_max: Optional[Sequence[float]] = None) -> None:
        super().__init__()
        if not (isinstance(eps, (int, float)) and eps >= 0):
            raise MSSFError(f"eps: expected a non-negative float, got {eps!r}")
        self.eps = float(eps)
        self.point_range_max = (
            None if point_range_max is None else check_triple(point_range_max, "point_range_max", float)
        )

    def forward(
        self,
        voxels: SparseVoxels,
        points: Tensor,
        points_batch: Tensor,
        lidar2img: Tensor,
        image_size: Sequence[int],
        points_to_sensor: Optional[Tensor] = None,
    ) -> CentroidProjection:
        if not isinstance(voxels, SparseVoxels):
            raise MSSFError(f"voxels: expected SparseVoxels, got {type(voxels).__name__}")
        l2i_batch = lidar2img.shape[0] if isinstance(lidar2img, Tensor) and lidar2img.dim() >= 3 else None
        if l2i_batch is not None and l2i_batch != voxels.batch_size:
            raise MSSFError(
                f"lidar2img: expected batch size {voxels.batch_size} (voxels.batch_size), "
                f"got shape {tuple(lidar2img.shape)}"
            )
        if points_to_sensor is not None:
            check_shape(points_to_sensor, "points_to_sensor", (voxels.batch_size, 4, 4))
        check_points(points, points_batch, exact_xyz=True)
        if points.dtype in (torch.float16, torch.bfloat16):
            # Centroids (sums of coordinates) and projections in half precision would be off by
            # decimetres and pixels: compute them in float32 (the coordinates themselves are exact).
            points = points.float()
        centroid, has_points = voxel_centroids(
            points, points_batch, voxels.coords, voxels.spatial_shape, voxels.batch_size,
            voxels.voxel_size, voxels.point_range_min, voxels.stride, self.point_range_max,
        )
        batch_index = voxels.batch_index
        proj = project_points(centroid, batch_index, lidar2img, image_size, points_to_sensor, self.eps)
        return CentroidProjection(
            uv=proj.uv, depth=proj.depth, valid=proj.valid, centroid=centroid,
            has_points=has_points, batch_index=batch_index,
        )

    def extra_repr(self) -> str:
        return f"eps={self.eps}, point_range_max={self.point_range_max}"


def augmentation_matrix(
    flip_x: bool = False,
    flip_y: bool = False,
    rotation: float = 0.0,
    scale: float = 1.0,
    translation: Sequence[float] = (0.0, 0.0, 0.0),
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """``(4, 4)`` global point-cloud augmentation as OpenPCDet/mmdet3d apply it, in that order.

    ``p' = T + s * Rz(rotation) * F * p`` where ``F`` flips y (``flip_x``: mirror across the x axis,
    ``y -> -y``) and/or x (``flip_y``: ``x -> -x``). Its inverse (``torch.linalg.inv``) is the
    ``points_to_sensor`` matrix that :class:`VoxelCentroidProjector` takes.
    """
    if not scale > 0:
        raise MSSFError(f"scale: expected a positive float, got {scale!r}")
    t = check_triple(translation, "translation", float)
    f = torch.eye(4, dtype=dtype)
    if flip_x:
        f[1, 1] = -1.0
    if flip_y:
        f[0, 0] = -1.0
    c, s = math.cos(rotation), math.sin(rotation)
    r = torch.eye(4, dtype=dtype)
    r[0, 0], r[0, 1], r[1, 0], r[1, 1] = c, -s, s, c
    m = r @ f
    m[:3, :3] *= scale
    m[:3, 3] = torch.tensor(t, dtype=dtype)
    return m
