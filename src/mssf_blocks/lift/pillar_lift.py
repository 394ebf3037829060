"""``PillarLift`` and ``HeightEmbedding``: run voxel fusion blocks inside a pillar (BEV) network.

Paper Sec. III-G ("Extend to Pillar"): ``f_vox = BEV(x, y) + HeightEmb(z)`` for every non-empty voxel
of the raw points voxelised at the BEV grid's x/y resolution; after fusion the voxel features with the
same ``(x, y)`` are summed back into the BEV map. See :mod:`mssf_blocks.functional.lift` for the pure
functions and ``docs/pillar.md`` for a walk-through.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple, Union

from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_shape, to_module_dtype
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.checks.agreement import check_channels
from mssf_blocks.errors import MSSFError
from mssf_blocks.checks.arguments import check_stride2
from mssf_blocks.functional.lift import (
    bev_shape_for,
    pillar_lift,
    voxels_to_bev,
    voxels_to_bev_sparse,
)
from mssf_blocks.lift.height_embedding import HeightEmbedding
from mssf_blocks.voxel_grid import VoxelGrid
from mssf_blocks.sparse_voxels import SparseVoxels

__all__ = ["PillarLift"]


class PillarLift(nn.Module):
    """Lift a BEV map into the non-empty voxels of a point cloud, and sum them back.

    ``forward(bev, voxels)`` gives the voxels (their coords; their own features are discarded) new
    features ``bev[b, :, y // sy, x // sx] + HeightEmb(z)``. :meth:`to_bev` sums voxel features with the
    same ``(b, y // sy, x // sx)`` into a ``(B, C, H_b, W_b)`` map, so ``to_bev(forward(bev, v))``
    lands on the grid of ``bev``.

    Args:
        channels: ``C`` of the BEV map.
        num_z: ``D`` of the voxel grid (number of height embeddings); or ``grid=``, the
            :class:`~mssf_blocks.VoxelGrid`, whose ``D`` it reads.
        stride: ``int`` or ``(sy, sx)``: the BEV map's stride relative to the voxel grid's x/y cells
            (the BEV map must be ``(B, C, ceil(H / sy), ceil(W / sx))`` for a voxel grid ``(D, H, W)``).
        use_height_embedding: False drops the height term (the paper's plain lift).
        raw_channels: ``None`` (the paper) or ``C_raw``: add a raw-voxel term, a bias-free 3x3x3
            submanifold convolution (spconv ``SubMConv3d``, :attr:`raw_conv`) of the voxels' own
            ``(N, C_raw)`` features, as the authors' MSSF-PP (``conv_input``, keys
            ``conv_input.0.weight``); the voxels' features are then read instead of discarded.
        use_bev: False drops the ``BEV(x, y)`` term (the authors' ``PointPillarsScatterFuse``, whose
            voxels are ``conv_input(radar voxels)`` only); needs ``raw_channels``.
        device, dtype: factory kwargs of the embedding (and of ``raw_conv``).

    Shapes:
        - bev: ``(B, C, H_b, W_b)``; voxels: :class:`SparseVoxels` with ``spatial_shape (D, H, W)``.
        - output: :class:`SparseVoxels` with ``features (N, C)``.

    Host synchronisation: one read-back in ``forward`` and in :meth:`to_bev` (the coordinate range
    checks, all at once); :meth:`to_bev_sparse` also sizes the occupied pillars (``torch.unique``).
    The backward has none.

    Example:
        >>> import torch
        >>> from mssf_blocks.functional.lift import voxelize_points
        >>> pts = torch.tensor([[0.1, 0.1, 0.2], [0.1, 0.1, 1.2], [1.5, 0.3, 0.2]])
        >>> vox = voxelize_points(pts, torch.zeros(3, dtype=torch.long), 1, (0.5, 0.5, 1.0),
        ...                       (0.0, 0.0, 0.0), (2.0, 1.0, 2.0))
        >>> lift = PillarLift(channels=1, num_z=2)
        >>> bev = torch.arange(8.0).reshape(1, 1, 2, 4)
        >>> lifted = lift(bev, vox)
        >>> lifted.features.flatten().tolist(), lift.to_bev(lifted).flatten().tolist()
        ([0.0, 3.0, 0.0], [0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    """

    def __init__(
        self,
        channels: int,
        num_z: Optional[int] = None,
        stride: Union[int, Sequence[int]] = 1,
        use_height_embedding: bool = True,
        device=None,
        dtype=None,
        raw_channels: Optional[int] = None,
        use_bev: bool = True,
        *,
        grid: Optional[VoxelGrid] = None,
    ) -> None:
        super().__init__()
        self.channels = check_positive_int(channels, "channels")
        if grid is not None:
            if not isinstance(grid, VoxelGrid):
                raise MSSFError(f"grid: expected a VoxelGrid, got {type(grid).__name__}")
            if num_z is not None and num_z != grid.spatial_shape[0]:
                raise MSSFError(f"num_z: expected {grid.spatial_shape[0]} (the grid's D, z cells), got {num_z}; "
                                "pass one of grid= and num_z=")
            num_z = grid.spatial_shape[0]
        if num_z is None:
            raise MSSFError("num_z: expected the voxel grid's D (z cells), or grid=VoxelGrid(...), got None")
        self.num_z = check_positive_int(num_z, "num_z")
        self.stride = check_stride2(stride)
        if not isinstance(use_height_embedding, bool):
            raise MSSFError(f"use_height_embedding: expected a bool, got {use_height_embedding!r}")
        if not isinstance(use_bev, bool):
            raise MSSFError(f"use_bev: expected a bool, got {use_bev!r}")
        if not use_bev and raw_channels is None:
            raise MSSFError("use_bev: False needs raw_channels (the voxels would have no feature at all)")
        self.use_bev = use_bev
        self.raw_conv = None
        if raw_channels is not None:
            raw_channels = check_positive_int(raw_channels, "raw_channels")
            import spconv.pytorch as spconv  # only for the authors' layout

            conv = spconv.SubMConv3d(raw_channels, channels, 3, padding=1, bias=False, indice_key="lift_raw")
            self.raw_conv = conv.to(device=device, dtype=dtype) if device is not None or dtype is not None else conv
        self.height_embedding = (
            HeightEmbedding(num_z, channels, device=device, dtype=dtype) if use_height_embedding else None
        )

    def bev_shape(self, voxels: SparseVoxels) -> Tuple[int, int]:
        """``(H_b, W_b)`` of the BEV map that matches ``voxels``' grid at this stride."""
        return bev_shape_for(voxels.spatial_shape[1:], self.stride)

    def _check_voxels(self, voxels: SparseVoxels) -> None:
        if not isinstance(voxels, SparseVoxels):
            raise MSSFError(f"voxels: expected SparseVoxels, got {type(voxels).__name__}")
        if voxels.spatial_shape[0] != self.num_z:
            raise MSSFError(
                f"voxels: expected spatial_shape[0] (D) = num_z = {self.num_z}, got spatial_shape "
                f"{voxels.spatial_shape}"
            )

    def forward(self, bev: Tensor, voxels: SparseVoxels) -> SparseVoxels:
        self._check_voxels(voxels)
        expected = (voxels.batch_size, self.channels) + self.bev_shape(voxels)
        check_shape(bev, "bev", ("B", "C", "H_b", "W_b"))
        check_channels(bev, "bev", self.channels, "PillarLift channels")
        if tuple(bev.shape) != expected:
            raise MSSFError(
                f"bev: expected shape (B, C, H_b, W_b) = {expected} for voxels with batch_size "
                f"{voxels.batch_size}, spatial_shape {voxels.spatial_shape} at stride {self.stride}, "
                f"got {tuple(bev.shape)}"
            )
        emb = None if self.height_embedding is None else self.height_embedding.weight
        if emb is not None:  # the dtype rule (docs/conventions.md): bev is read in the embedding's dtype
            bev = to_module_dtype(bev, "bev", emb.dtype, "PillarLift")
        if not self.use_bev:
            feats = emb[voxels.coords[:, 1].long()] if emb is not None else None
        else:
            feats = pillar_lift(bev, voxels.coords, emb, self.stride)
        if self.raw_conv is not None:
            c_raw = self.raw_conv.in_channels
            if voxels.features.dim() != 2 or voxels.features.shape[1] != c_raw:
                raise MSSFError(f"voxels: expected raw voxel features (N, {c_raw}) for raw_conv (PillarLift "
                                f"raw_channels={c_raw}), got {tuple(voxels.features.shape)}; build the lift with "
                                f"raw_channels={voxels.features.shape[-1]}, or pass {c_raw}-channel voxels")
            w = self.raw_conv.weight
            raw = self.raw_conv(voxels.replace(features=to_module_dtype(voxels.features, "voxels.features", w.dtype,
                                                                        "PillarLift")).to_spconv()).features
            feats = raw if feats is None else raw + feats.to(raw.dtype)
        return voxels.replace(features=feats)

    def to_bev(self, voxels: SparseVoxels) -> Tensor:
        """``(B, C', H_b, W_b)``: voxel features summed per ``(b, y // sy, x // sx)``."""
        if not isinstance(voxels, SparseVoxels):
            raise MSSFError(f"voxels: expected SparseVoxels, got {type(voxels).__name__}")
        return voxels_to_bev(voxels.features, voxels.coords, voxels.batch_size, self.bev_shape(voxels),
                             self.stride)

    def to_bev_sparse(self, voxels: SparseVoxels) -> Tuple[Tensor, Tensor]:
        """Occupied pillars only: ``features (M, C')`` and ``coords (M, 3)`` int32 ``(b, y, x)``."""
        if not isinstance(voxels, SparseVoxels):
            raise MSSFError(f"voxels: expected SparseVoxels, got {type(voxels).__name__}")
        return voxels_to_bev_sparse(voxels.features, voxels.coords, voxels.batch_size,
                                    self.bev_shape(voxels), self.stride)

    def extra_repr(self) -> str:
        return (f"channels={self.channels}, num_z={self.num_z}, stride={self.stride}, "
                f"use_height_embedding={self.height_embedding is not None}, use_bev={self.use_bev}, "
                f"raw_channels={None if self.raw_conv is None else self.raw_conv.in_channels}")
