"""``QueryInit``: the first MSDFF block's query (paper eq. 8), ``Linear_BN(cat(f_vox, f_img^1, p))``."""

from __future__ import annotations

from typing import Optional, Sequence, Type, Union

import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_floating, check_shape, to_module_dtype
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.checks.agreement import check_batch_statistics, check_channels
from mssf_blocks.samplers._layers import _factory, _norm
from mssf_blocks.errors import MSSFError
from mssf_blocks.checks.arguments import check_grid_argument, check_point_cloud_range
from mssf_blocks.voxel_grid import VoxelGrid

__all__ = ["QueryInit"]

_QUERY_POSITIONS = ("voxel_centre", "centroid")


class QueryInit(nn.Module):
    """MSDFF query initialisation (paper eq. 8): ``Linear_BN(cat(f_vox, f_img^1, p))``.

    Args:
        voxel_channels: ``C_v`` of ``f_vox``.
        image_channels: ``C_i`` of ``f_img^1`` (the first image level sampled at the centroid).
        out_channels: query channels (the MSDFF ``embed_dim``).
        point_cloud_range: the voxels' :class:`~mssf_blocks.VoxelGrid` (also as ``grid=``), or its 6 values
            ``(x_min, y_min, z_min, x_max, y_max, z_max)``: they normalise voxel centres to ``p`` in ``[0, 1]^3``.
            :class:`~mssf_blocks.FusionBlock` builds one itself with ``query_init=True``.
        norm_layer: normalisation after the linear layer (``None``: none).
        device, dtype: factory arguments of the parameters.
        position: what :class:`~mssf_blocks.blocks.FusionBlock` passes as ``centers``:
            ``"voxel_centre"`` (default; the paper's eq. 8 position of the voxel) or ``"centroid"`` (the
            centroid of the voxel's points, its centre where it holds none: the MSSF authors' code).
        align_corners: how :class:`~mssf_blocks.blocks.FusionBlock` samples ``f_img^1``: as
            :func:`sample_at_projection` (``True``: the authors' ``align_corners=True``).

    The columns of ``linear.weight`` are ``[f_vox | f_img^1 | p]``; the authors' ``query_proj`` reads
    ``[f_img^1 | f_vox | p]`` (:mod:`mssf_blocks.weights.authors_checkpoint` permutes them on loading).

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
        point_cloud_range: Union[Sequence[float], VoxelGrid, None] = None,
        norm_layer: Optional[Type[nn.Module]] = nn.BatchNorm1d,
        device=None,
        dtype=None,
        position: str = "voxel_centre",
        align_corners: bool = False,
        *,
        grid: Optional[VoxelGrid] = None,
    ) -> None:
        super().__init__()
        if isinstance(point_cloud_range, VoxelGrid):
            point_cloud_range, grid = None, point_cloud_range if grid is None else grid
        if check_grid_argument(grid, point_cloud_range, "point_cloud_range") is not None:
            point_cloud_range = grid.point_cloud_range
        if point_cloud_range is None:
            raise MSSFError("grid: expected the voxels' VoxelGrid (or point_cloud_range=, its 6 values), got None")
        if position not in _QUERY_POSITIONS:
            raise MSSFError(f"position: expected one of {_QUERY_POSITIONS}, got {position!r}")
        if not isinstance(align_corners, bool):
            raise MSSFError(f"align_corners: expected a bool, got {align_corners!r}")
        self.position, self.align_corners = position, align_corners
        self.voxel_channels = check_positive_int(voxel_channels, "voxel_channels")
        self.image_channels = check_positive_int(image_channels, "image_channels")
        self.out_channels = check_positive_int(out_channels, "out_channels")
        pcr = check_point_cloud_range(point_cloud_range)
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
