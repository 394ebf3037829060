"""Pure-torch dynamic voxelisation and PointPillars' pillar feature net (CPU and GPU alike).

* :func:`dynamic_voxelize` groups points by their voxel with one ``torch.unique`` over a linear key
  (no fixed ``max_points``/``max_voxels`` caps, so nothing is dropped except points outside the range,
  which the returned ``keep`` mask reports) and averages the point features of every voxel.
* :class:`PillarFeatureNet` is the pillar feature net of PointPillars (Lang et al., CVPR 2019): every
  point is decorated with its offset to the mean of its pillar and to the pillar centre, passed
  through ``Linear - BatchNorm1d - ReLU`` and max-pooled over its pillar.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple, Type

import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.lift import voxels_to_bev
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.voxel_grid import VoxelGrid  # (the library's grid: one grid description for the library and the examples)

__all__ = [
    "VoxelGrid",
    "Voxelization",
    "dynamic_voxelize",
    "DynamicVoxelizer",
    "pillar_feature_net",
    "PillarFeatureNet",
    "pillars_to_bev",
]


@dataclass
class Voxelization:
    """Result of :func:`dynamic_voxelize`.

    Attributes:
        features: ``(N, C)`` mean of the point features of every non-empty voxel.
        coords: ``(N, 4)`` int32 ``(batch, z, y, x)``, sorted by linear key (batch-major).
        point_voxel: ``(P_kept,)`` int64 row of ``coords`` of every kept point.
        keep: ``(P,)`` bool, the points inside the range (the only points that are not used).
        num_points: ``(N,)`` int64 number of points in every voxel.
    """

    features: Tensor
    coords: Tensor
    point_voxel: Tensor
    keep: Tensor
    num_points: Tensor


def _check_points(points: Tensor, points_batch: Tensor, batch_size: int) -> None:
    dims: dict = {}
    check_shape(points, "points", ("P", None), dims)
    check_floating(points, "points")
    if points.shape[1] < 3:
        raise MSSFError(f"points: expected at least 3 columns (x, y, z), got shape {tuple(points.shape)}")
    check_shape(points_batch, "points_batch", ("P",), dims)
    if points_batch.is_floating_point():
        raise MSSFError(f"points_batch: expected an integer tensor, got dtype {points_batch.dtype}")
    check_positive_int(batch_size, "batch_size")
    if points_batch.numel() and (int(points_batch.min()) < 0 or int(points_batch.max()) >= batch_size):
        raise MSSFError(
            f"points_batch: expected values in [0, {batch_size}) (batch_size={batch_size}), got values in "
            f"[{int(points_batch.min())}, {int(points_batch.max())}]"
        )
    if points.numel() and not bool(torch.isfinite(points[:, :3]).all()):
        raise MSSFError("points: expected finite x, y, z, got NaN/inf entries")


def _voxel_index(points: Tensor, grid: VoxelGrid) -> Tuple[Tensor, Tensor]:
    """``(P, 3)`` int64 ``(x, y, z)`` voxel index and ``(P,)`` in-range mask."""
    lo = torch.tensor(grid.point_cloud_range[:3], dtype=points.dtype, device=points.device)
    vs = torch.tensor(grid.voxel_size, dtype=points.dtype, device=points.device)
    idx = torch.floor((points[:, :3] - lo) / vs).long()
    size = torch.tensor(grid.grid_size, device=points.device)
    keep = ((idx >= 0) & (idx < size)).all(1)
    return idx, keep


def dynamic_voxelize(points: Tensor, points_batch: Tensor, batch_size: int, grid: VoxelGrid) -> Voxelization:
    """Group points into voxels and average their features.

    Args:
        points: ``(P, C)`` points, columns 0..2 metric ``(x, y, z)``.
        points_batch: ``(P,)`` integer sample index of every point.
        batch_size: ``B``.
        grid: the voxel grid; points outside ``[min, max)`` on any axis are not used (see ``keep``).

    Returns:
        :class:`Voxelization` (voxel features are the mean of the point features, all ``C`` columns).
    """
    _check_points(points, points_batch, batch_size)
    idx, keep = _voxel_index(points, grid)
    pts, idx, b = points[keep], idx[keep], points_batch[keep].long()
    nx, ny, nz = grid.grid_size
    key = ((b * nz + idx[:, 2]) * ny + idx[:, 1]) * nx + idx[:, 0]
    uniq, inverse, counts = torch.unique(key, sorted=True, return_inverse=True, return_counts=True)
    n = uniq.numel()
    feats = pts.new_zeros(n, pts.shape[1]).index_add_(0, inverse, pts) / counts.unsqueeze(1).to(pts.dtype)
    x = uniq % nx
    rest = uniq // nx
    y = rest % ny
    rest = rest // ny
    z = rest % nz
    bb = rest // nz
    coords = torch.stack([bb, z, y, x], 1).int()
    return Voxelization(features=feats, coords=coords, point_voxel=inverse, keep=keep, num_points=counts)


class DynamicVoxelizer(nn.Module):
    """Mean-of-points dynamic voxelisation returning :class:`SparseVoxels`.

    Args:
        point_cloud_range: ``(x0, y0, z0, x1, y1, z1)`` metres.
        voxel_size: ``(x, y, z)`` metres.

    Shapes:
        - points ``(P, C)``, points_batch ``(P,)`` -> SparseVoxels with ``(N, C)`` features.
    """

    def __init__(self, point_cloud_range: Sequence[float], voxel_size: Sequence[float]) -> None:
        super().__init__()
        self.grid = VoxelGrid(voxel_size=tuple(voxel_size), point_cloud_range=tuple(point_cloud_range))

    def forward(self, points: Tensor, points_batch: Tensor, batch_size: int) -> SparseVoxels:
        vox = dynamic_voxelize(points, points_batch, batch_size, self.grid)
        return SparseVoxels(vox.features, vox.coords, batch_size=batch_size, grid=self.grid)

    def extra_repr(self) -> str:
        return f"point_cloud_range={self.grid.point_cloud_range}, voxel_size={self.grid.voxel_size}"


def pillar_feature_net(
    points: Tensor,
    points_batch: Tensor,
    batch_size: int,
    grid: VoxelGrid,
    linear: nn.Linear,
    norm: nn.Module,
    vox: Optional[Voxelization] = None,
    max_points: Optional[int] = None,
) -> Tuple[Tensor, Voxelization]:
    """Pillar features: decorate points, ``Linear - norm - ReLU``, max over each pillar.

    ``grid`` must have a single z cell (a pillar spans the whole height). Each point becomes
    ``[point (C), xyz - pillar mean (3), xyz - pillar centre (3)]``. ``vox``: the pillars'
    :func:`dynamic_voxelize` when computed already (``None``: computed here). ``max_points``: ``None``, or
    mmdet3d's hard-voxelisation padding (``max_num_points``): a pillar of fewer points also gets its
    zero-padded rows, ``relu(norm(linear(0)))``, into the max (and the norm sees them in training),
    as mmdet3d's ``PillarFeatureNet``.

    Returns:
        ``(N, C_out)`` pillar features and the :class:`Voxelization` of the pillars.
    """
    if grid.grid_size[2] != 1:
        raise MSSFError(f"grid: a pillar grid needs one z cell, got grid_size {grid.grid_size}")
    if vox is None:
        vox = dynamic_voxelize(points, points_batch, batch_size, grid)
    pts = points[vox.keep]
    xyz = pts[:, :3]
    mean = vox.features[vox.point_voxel, :3]
    vs = torch.tensor(grid.voxel_size, dtype=pts.dtype, device=pts.device)
    lo = torch.tensor(grid.point_cloud_range[:3], dtype=pts.dtype, device=pts.device)
    cell = vox.coords[vox.point_voxel][:, [3, 2, 1]].to(pts.dtype)
    centre = (cell + 0.5) * vs + lo
    decorated = torch.cat([pts, xyz - mean, xyz - centre], 1)
    pad = 0
    if max_points is not None:
        short = vox.num_points < max_points
        pad = int((max_points - vox.num_points[short]).sum())
        decorated = torch.cat([decorated, decorated.new_zeros(pad, decorated.shape[1])])
    x = torch.relu(norm(linear(decorated)))
    out = x.new_zeros(vox.coords.shape[0], x.shape[1])
    n = x.shape[0] - pad
    out = out.scatter_reduce(0, vox.point_voxel.unsqueeze(1).expand(n, x.shape[1]), x[:n], "amax", include_self=False)
    if pad:  # every padded row gives the same vector
        out = torch.where(short[:, None], torch.maximum(out, x[-1]), out)
    return out, vox


class PillarFeatureNet(nn.Module):
    """PointPillars' pillar feature net (one PFN layer: ``Linear - BN - ReLU`` then max).

    Args:
        in_channels: point feature columns ``C`` (including x, y, z).
        out_channels: pillar feature channels.
        point_cloud_range: ``(x0, y0, z0, x1, y1, z1)``.
        pillar_size: ``(x, y)`` metres (a pillar spans the whole z range).
        norm_layer: normalisation type over ``(P, C_out)``.
        max_points: ``None`` (the max over a pillar's points), or the authors' / mmdet3d's hard
            voxelisation ``max_num_points``: pillars of fewer points also take their zero-padded rows
            into the max (see :func:`pillar_feature_net`). Points beyond it are not dropped here.

    Shapes:
        - points ``(P, C)``, points_batch ``(P,)`` -> SparseVoxels ``(N, out_channels)`` on a grid with
          ``spatial_shape (1, ny, nx)`` and ``voxel_size (px, py, z extent)``.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        point_cloud_range: Sequence[float],
        pillar_size: Sequence[float],
        norm_layer: Type[nn.Module] = nn.BatchNorm1d,
        device=None,
        dtype=None,
        max_points: Optional[int] = None,
    ) -> None:
        super().__init__()
        check_positive_int(in_channels, "in_channels")
        check_positive_int(out_channels, "out_channels")
        self.max_points = None if max_points is None else check_positive_int(max_points, "max_points")
        pcr = tuple(float(v) for v in point_cloud_range)
        if len(tuple(pillar_size)) != 2:
            raise MSSFError(f"pillar_size: expected (x, y), got {pillar_size!r}")
        self.in_channels = in_channels
        self.grid = VoxelGrid(voxel_size=(float(pillar_size[0]), float(pillar_size[1]), pcr[5] - pcr[2]), point_cloud_range=pcr)
        # BN follows, so the bias would be redundant (as in PointPillars).
        self.linear = nn.Linear(in_channels + 6, out_channels, bias=False, device=device, dtype=dtype)
        self.norm = norm_layer(out_channels, device=device, dtype=dtype)

    def forward(self, points: Tensor, points_batch: Tensor, batch_size: int,
                voxelization: Optional[Voxelization] = None) -> SparseVoxels:
        if points.dim() == 2 and points.shape[1] != self.in_channels:
            raise MSSFError(f"points: expected {self.in_channels} columns, got shape {tuple(points.shape)}")
        feats, vox = pillar_feature_net(points, points_batch, batch_size, self.grid, self.linear, self.norm,
                                        voxelization, self.max_points)
        return SparseVoxels(feats, vox.coords, batch_size=batch_size, grid=self.grid)

    def extra_repr(self) -> str:
        return (
            f"in_channels={self.in_channels}, out_channels={self.linear.out_features}, "
            f"point_cloud_range={self.grid.point_cloud_range}, pillar_size={self.grid.voxel_size[:2]}"
        )


def pillars_to_bev(pillars: SparseVoxels) -> Tensor:
    """Scatter pillar features into a dense ``(B, C, H, W)`` BEV map (rows = y, columns = x).

    Voxels with the same ``(b, y, x)`` (any z) are summed, so this also collapses a 3D tensor.
    """
    # (the library's sum into the transposed view of the NCHW map: its earlier copy here built a
    # (B*H*W, C) table and made it channels-first, 45 ms a VoD frame of 320 x 320 x 64 on one core)
    return voxels_to_bev(pillars.features, pillars.coords, pillars.batch_size, pillars.spatial_shape[1:])
