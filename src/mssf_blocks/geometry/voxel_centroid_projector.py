"""``VoxelCentroidProjector``: voxel centroids of a sparse tensor, projected into the cameras.

This is the first half of every MSSF fusion block (paper Sec. III-C, eq. 1-2): find the centroid of
the raw points inside each non-empty voxel (its centre if it holds none), then project it with the
camera matrices to normalised image coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_points, check_shape
from mssf_blocks.checks.arguments import check_triple
from mssf_blocks.checks.coverage import RunningCoverage
from mssf_blocks.checks.first_call import (
    check_image_size_small,
    check_points_in_voxels,
    check_points_to_sensor,
    project_raw,
)
from mssf_blocks.checks.geometry import (
    check_centroid_coverage,
    check_projection_coverage,
    geometry_checks_enabled,
    set_geometry_checks,
)
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.geometry import project_points, voxel_centroids
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.static_path import register_pytree
from mssf_blocks.checks.arguments import check_grid_argument
from mssf_blocks.voxel_grid import VoxelGrid

__all__ = ["VoxelCentroidProjector", "CentroidProjection", "set_geometry_checks"]


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


# torch.export / ONNX: every field is a graph input / output tensor
register_pytree(CentroidProjection, ("uv", "depth", "valid", "centroid", "has_points", "batch_index"), ())


class VoxelCentroidProjector(nn.Module):
    """Centroids of a :class:`SparseVoxels` projected into ``V`` cameras.

    Args:
        eps: depths ``<= eps`` are invalid (behind the camera).
        point_range_max: optional ``(x, y, z)`` upper corner of the point-cloud range; points at or
            above it are ignored (by default, points beyond the voxels' grid are ignored).
        grid: a :class:`~mssf_blocks.VoxelGrid` instead of ``point_range_max`` (its upper corner).
        half_pixel: ``True`` (default): ``uv = ((u + 0.5) / W, (v + 0.5) / H)``, pixel ``i``'s centre at
            ``(i + 0.5) / W`` (every FPN level samples the same spot). ``False``: ``uv = (u / W, v / H)``,
            the paper's ``c = (u / W, v / H)`` taken literally and the MSSF authors' reference points
            (half a base pixel to the left and up; :mod:`mssf_blocks.weights.authors_checkpoint`).
        inside_image_only: ``True`` (default): ``valid`` needs the point inside the image; a voxel
            outside gets an exact zero image feature. ``False``: ``valid`` is ``depth > eps`` only, so
            an out-of-image voxel in front of the camera is sampled (zero padding; MSDFF offsets may
            reach into the image) and goes through the samplers' output layers, as in the authors'
            code.

    Shapes:
        - voxels: N voxels at any stride; points ``(P, 3)`` x, y, z (slice other columns off: extra
          columns are refused); points_batch ``(P,)``.
        - lidar2img ``(B, V, 3, 4)`` or ``(B, 3, 4)``; points_to_sensor ``(B, 4, 4)``.
        - output: :class:`CentroidProjection` with ``uv (N, V, 2)``, ``depth (N, V)``, ``valid (N, V)``,
          ``centroid (N, 3)``, ``has_points (N,)``, in the dtype of ``points`` (float32 for float16 /
          bfloat16 points: half-precision centroids would be off by decimetres).

    Example:
        >>> import torch
        >>> from mssf_blocks import SparseVoxels, VoxelCentroidProjector, VoxelGrid
        >>> grid = VoxelGrid(voxel_size=(1.0, 1.0, 1.0), point_cloud_range=(0, 0, 0, 1, 1, 1))
        >>> vox = SparseVoxels(torch.zeros(1, 2), torch.tensor([[0, 0, 0, 0]], dtype=torch.int32),
        ...                    batch_size=1, grid=grid, stride=(1, 1, 1))
        >>> pts = torch.tensor([[0.25, 0.5, 0.75]])
        >>> l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]])  # depth 1, u = x, v = y
        >>> out = VoxelCentroidProjector()(vox, pts, torch.zeros(1, dtype=torch.long), l2i, (4, 4))
        >>> out.centroid, out.uv
        (tensor([[0.2500, 0.5000, 0.7500]]), tensor([[[0.1875, 0.2500]]]))
    """

    def __init__(self, eps: float = 1e-5, point_range_max: Optional[Sequence[float]] = None,
                 half_pixel: bool = True, inside_image_only: bool = True, *,
                 grid: Optional[VoxelGrid] = None) -> None:
        super().__init__()
        if check_grid_argument(grid, point_range_max, "point_range_max") is not None:
            point_range_max = grid.point_range_max
        for name, flag in (("half_pixel", half_pixel), ("inside_image_only", inside_image_only)):
            if not isinstance(flag, bool):
                raise MSSFError(f"{name}: expected a bool, got {flag!r}")
        self.half_pixel, self.inside_image_only = half_pixel, inside_image_only
        if not (isinstance(eps, (int, float)) and eps >= 0):
            raise MSSFError(f"eps: expected a non-negative float, got {eps!r}")
        self.eps = float(eps)
        self.point_range_max = (
            None if point_range_max is None else check_triple(point_range_max, "point_range_max", float)
        )
        #: running per-sample coverage (in-image and centroid fractions) per voxel stride, for the
        #: collapse warnings (docs/conventions.md, "Common mistakes"); plain numbers, not in the state_dict
        self.coverage = RunningCoverage()

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
        uv, valid = proj.uv, proj.valid
        # (warnings; they read data only where that costs no host synchronisation: _sanity's doc)
        checks = geometry_checks_enabled(uv) and uv.shape[0] > 0 and points.shape[0] > 0
        raw_uv, raw_inside = (project_raw(points, points_batch, lidar2img, image_size, points_to_sensor, self.eps)
                              if checks else (None, None))
        check_projection_coverage(uv, proj.depth, batch_index, voxels.batch_size, image_size, lidar2img, self.eps,
                                  getattr(self, "coverage", None), voxels.stride,
                                  raw_uv=None if raw_uv is None else raw_uv[raw_inside])
        check_centroid_coverage(has_points, batch_index, points_batch, voxels.batch_size,
                                getattr(self, "coverage", None), voxels.stride)
        if checks:  # first-call consistency of voxels, points and points_to_sensor (_first_call's doc)
            check_points_in_voxels(points, points_batch, voxels.coords, batch_index, voxels.spatial_shape,
                                   voxels.batch_size, voxels.voxel_size, voxels.point_range_min, voxels.stride,
                                   self.point_range_max, has_points)
            check_image_size_small(raw_uv, raw_inside, lidar2img, image_size)
            if points_to_sensor is not None:
                check_points_to_sensor(points, points_batch, lidar2img, image_size, points_to_sensor, raw_inside,
                                       voxels.batch_size, self.eps)
        ok_depth = proj.depth > self.eps
        if not self.half_pixel:  # u / W (project_points validated image_size)
            h, w = (int(x) for x in image_size)
            uv = proj.pixel / torch.tensor([w, h], dtype=proj.pixel.dtype, device=proj.pixel.device)
            uv = torch.where(ok_depth[..., None], uv, torch.full_like(uv, -1.0))
        if not self.inside_image_only:
            valid = ok_depth
        elif not self.half_pixel:  # inside the image in the u / W coordinates
            valid = ok_depth & (uv >= 0).all(dim=-1) & (uv <= 1).all(dim=-1)
        return CentroidProjection(
            uv=uv, depth=proj.depth, valid=valid, centroid=centroid,
            has_points=has_points, batch_index=batch_index,
        )

    def extra_repr(self) -> str:
        extra = "" if self.half_pixel and self.inside_image_only else (
            f", half_pixel={self.half_pixel}, inside_image_only={self.inside_image_only}")
        return f"eps={self.eps}, point_range_max={self.point_range_max}{extra}"
