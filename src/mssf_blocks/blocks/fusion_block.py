"""``FusionBlock``: an ordinary sparse-backbone stage with MSSF image fusion inside it.

Paper: *MSSF*, Sec. III-C ("General Fusion Block", eq. 1-5). An ordinary block of SECOND / VoxelNeXt /
OpenPCDet's ``VoxelResBackBone8x`` is a downsampling sparse convolution followed by residual blocks.
A fusion block keeps both parts and inserts, between them (``position="before_residual"``, as in the
paper) or after them (``"after_residual"``):

1. voxel centroids projected into the cameras (:class:`~mssf_blocks.geometry.VoxelCentroidProjector`);
2. an image sampler, :class:`~mssf_blocks.samplers.SFF` or :class:`~mssf_blocks.samplers.MSDFF` (the
   first MSDFF block builds its query with :class:`~mssf_blocks.samplers.QueryInit`);
3. ``f_fuse = f_vox + f_img`` (eq. 5) - the voxel set is unchanged, only features are replaced;
4. optionally the semantic-guided head (:class:`~mssf_blocks.heads.SemanticGuidedHead`, Sec. III-D)
   on the fused voxels, ``f_fuse' = f_fuse * s_seg``, right after the fusion and before the residual
   blocks (``head_position="after_fusion"``: the paper's eq. 12-13 read ``f_fuse``, and the authors'
   ``SparseEncoderVoxelNeXtFuse`` does it there) or after the residual blocks (``"after_residual"``).

The block takes and returns either a :class:`~mssf_blocks.sparse_voxels.SparseVoxels` or an spconv
``SparseConvTensor`` (whichever it was given). Because fusion never changes the voxel set, the spconv
tensor keeps its index cache (``indice_dict``), so later ``SubMConv3d`` / inverse convolutions that
reuse an ``indice_key`` keep working. spconv is imported only when a conversion needs it.
"""

from __future__ import annotations

import warnings
from typing import Any, Optional, Sequence, Tuple, Union

import torch
from torch import nn

from mssf_blocks.blocks._downsample_stride import infer_downsample_stride
from mssf_blocks.blocks.fusion_block_output import FusionBlockOutput
from mssf_blocks.checks.agreement import camera_batch_entries, check_agreement, query_range_mismatch
from mssf_blocks.checks.geometry import check_grid, check_indices_in_shape
from mssf_blocks.checks.image_features import check_image_features
from mssf_blocks.checks.spconv_inputs import check_sparse_tensor
from mssf_blocks.checks.tensors import is_tracing, to_module_dtype
from mssf_blocks.checks.arguments import check_triple
from mssf_blocks.errors import MSSFError, MSSFGeometryWarning
from mssf_blocks.functional.geometry import voxel_centroids
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection, VoxelCentroidProjector
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit, sample_at_projection
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.voxel_grid import VoxelGrid

__all__ = ["FusionBlock", "FusionBlockOutput", "infer_downsample_stride"]

_POSITIONS = ("before_residual", "after_residual")


def _is_spconv_tensor(x: Any) -> bool:
    """Whether ``x`` is an spconv ``SparseConvTensor`` (by its attributes: spconv need not be imported)."""
    return all(hasattr(x, a) for a in ("features", "indices", "spatial_shape", "batch_size", "replace_feature"))
_HEAD_POSITIONS = ("after_fusion", "after_residual")


class FusionBlock(nn.Module):
    """A sparse-backbone stage (downsample + residual blocks) with MSSF image fusion.

    Args:
        fusion: the image sampler, :class:`SFF` or :class:`MSDFF`; its ``out_channels`` are the voxel
            channels at the fusion step (the stage's channels).
        grid: the :class:`~mssf_blocks.VoxelGrid` of the model (``voxel_size`` + ``point_cloud_range``).
            Needed for an spconv input (it carries no metres; its stride is read from its ``spatial_shape``
            against the grid) and for ``query_init=True``; a :class:`SparseVoxels` input carries its own
            grid, which must then have this one's voxel size and lower corner.
        downsample: the stage's downsampling part (e.g. ``SparseConv3d`` + norm + ReLU), run on an
            spconv tensor; ``None`` for none.
        blocks: the stage's residual blocks (e.g. ``SparseBasicBlock`` s), run on an spconv tensor.
        position: ``"before_residual"`` (paper: fuse between downsample and residual blocks) or
            ``"after_residual"`` (fuse after the residual blocks).
        query_init: MSDFF only. ``True``: the block builds its :class:`QueryInit` (the first fusion block,
            eq. 8) from what it knows: the fusion's channels and ``grid``. A :class:`QueryInit`: that one
            (e.g. ``position="centroid"``, the authors' variant). ``None`` / ``False``: the query is the
            voxel feature itself.
        downsample_stride: ``(sz, sy, sx)`` of ``downsample``; inferred from its spconv convolutions
            when ``None``; when given, it must equal the inferred one where ``downsample`` holds spconv
            convolutions (a contradiction is refused).
        projector: the centroid projector (default ``VoxelCentroidProjector()``).
        semantic_head: a :class:`~mssf_blocks.heads.SemanticGuidedHead` to run in this block (the
            paper puts it in the last fusion block), or ``None``.
        head_position: where the head reads the voxels: ``"after_fusion"`` (default; the fused
            features ``f_fuse`` before the residual blocks, as the paper's eq. 12-13 and the authors'
            code) or ``"after_residual"`` (the block's output). With ``position="after_residual"``
            the fusion is the block's last step and both places are the same.

    ``forward(x, inputs, return_logits=False)``: ``x`` a :class:`SparseVoxels` or spconv
    ``SparseConvTensor``, ``inputs`` a :class:`FusionInputs`; returns the same type as ``x`` at stride
    ``x's stride * downsample_stride``. With ``return_logits=True`` (needs ``semantic_head``) it returns a
    :class:`FusionBlockOutput`: ``(out, head_voxels, logits)`` (unpacks as three: the
    :class:`SparseVoxels` the head read and its ``(N,)`` logits) with ``.centroids`` and ``.batch_index``
    of those voxels for the head's labels. ``query_add``: see :meth:`fuse` (the voxels reaching the fusion
    must be those of ``x``: a block without ``downsample``).
    The fused features are in the fusion's parameter dtype; voxel features of lower precision are read
    in it, float64 ones into a non-float64 block are refused (``docs/conventions.md``, "Dtypes").

    Host synchronisation: the centroid join (``torch.unique`` over voxel and point keys: a
    data-dependent size) and the range checks of the points and of voxels built from an spconv tensor
    (one read-back each), plus the sampler's (see :class:`SFF`, :class:`MSDFF`). Inherent to voxel sets.
    """

    def __init__(
        self,
        fusion: Union[SFF, MSDFF],
        grid: Optional[VoxelGrid] = None,
        downsample: Optional[nn.Module] = None,
        blocks: Optional[nn.Module] = None,
        position: str = "before_residual",
        query_init: Union[None, bool, QueryInit] = None,
        downsample_stride: Optional[Sequence[int]] = None,
        projector: Optional[VoxelCentroidProjector] = None,
        semantic_head: Optional[nn.Module] = None,
        head_position: str = "after_fusion",
    ) -> None:
        super().__init__()
        if not isinstance(fusion, (SFF, MSDFF)):
            raise MSSFError(f"fusion: expected an SFF or MSDFF module, got {type(fusion).__name__}")
        if grid is not None and not isinstance(grid, VoxelGrid):
            hint = (" (the second argument is the grid now: pass downsample= by keyword)"
                    if isinstance(grid, nn.Module) else "")
            raise MSSFError(f"grid: expected a VoxelGrid or None, got {type(grid).__name__}{hint}")
        self.grid = grid
        if position not in _POSITIONS:
            raise MSSFError(f"position: expected one of {_POSITIONS}, got {position!r}")
        if head_position not in _HEAD_POSITIONS:
            raise MSSFError(f"head_position: expected one of {_HEAD_POSITIONS}, got {head_position!r}")
        if semantic_head is not None:
            from mssf_blocks.heads.semantic_guided_head import SemanticGuidedHead

            if not isinstance(semantic_head, SemanticGuidedHead):
                raise MSSFError(f"semantic_head: expected a SemanticGuidedHead or None, got {type(semantic_head).__name__}")
            fused = fusion.out_channels
            if semantic_head.in_channels != fused:
                raise MSSFError(f"semantic_head: expected in_channels={fused} (the fused voxel channels), "
                                f"got {semantic_head.in_channels}")
        for name, part in (("downsample", downsample), ("blocks", blocks)):
            if part is not None and not isinstance(part, nn.Module):
                raise MSSFError(f"{name}: expected an nn.Module or None, got {type(part).__name__}")
        if query_init is False:
            query_init = None
        if query_init is True:
            if not isinstance(fusion, MSDFF):
                raise MSSFError("query_init: only an MSDFF fusion takes a query; got query_init=True with SFF")
            if grid is None:
                raise MSSFError("query_init: True builds a QueryInit from the block's grid (its range normalises "
                                "the query positions); construct FusionBlock with grid=VoxelGrid(...)")
            query_init = QueryInit(fusion.out_channels, fusion.in_channels, fusion.out_channels, grid=grid,
                                   device=fusion.output_proj.weight.device, dtype=fusion.output_proj.weight.dtype)
        if query_init is not None:
            if not isinstance(fusion, MSDFF):
                raise MSSFError("query_init: only an MSDFF fusion takes a query; got query_init with SFF")
            if not isinstance(query_init, QueryInit):
                raise MSSFError(f"query_init: expected a QueryInit, got {type(query_init).__name__}")
            if query_init.out_channels != fusion.embed_dim:
                raise MSSFError(
                    f"query_init: expected out_channels={fusion.embed_dim} (fusion.embed_dim), "
                    f"got {query_init.out_channels}"
                )
            if query_init.image_channels != fusion.value_channels:
                raise MSSFError(
                    f"query_init: expected image_channels={fusion.value_channels} (channels of image level 0), "
                    f"got {query_init.image_channels}"
                )
        self.fusion = fusion
        self.downsample = downsample
        self.blocks = blocks
        self.query_init = query_init
        self.position = position
        self.semantic_head = semantic_head
        self.head_position = head_position
        self.projector = projector if projector is not None else VoxelCentroidProjector()
        self.downsample_stride = (
            infer_downsample_stride(downsample)
            if downsample_stride is None
            else check_triple(downsample_stride, "downsample_stride", int, positive=True)
        )
        if downsample_stride is not None and downsample is not None:
            try:
                inferred = infer_downsample_stride(downsample)
            except MSSFError:  # no spconv convolution to read (or an inverse one): the explicit stride stands
                inferred = None
            if inferred is not None and inferred != self.downsample_stride:
                raise MSSFError(
                    f"downsample_stride: expected {inferred} (the product of the strides of downsample's spconv "
                    f"convolutions, (sz, sy, sx)), got {self.downsample_stride}; the output voxels would be "
                    "placed at the wrong stride. Leave it None to infer it"
                )
        if downsample is None and self.downsample_stride != (1, 1, 1):
            raise MSSFError(
                f"downsample_stride: expected (1, 1, 1) without a downsample module, got {self.downsample_stride}"
            )
    @property
    def out_channels(self) -> int:
        return self.fusion.out_channels

    def output_stride(self, in_stride: Sequence[int]) -> Tuple[int, int, int]:
        """``in_stride * downsample_stride`` per axis ``(sz, sy, sx)``."""
        return tuple(int(a) * b for a, b in zip(in_stride, self.downsample_stride))

    # -- the fusion step (eq. 1-5) on a fixed voxel set ---------------------------------------------
    def fuse(self, voxels: SparseVoxels, inputs: FusionInputs, query_add: Optional[torch.Tensor] = None) -> SparseVoxels:
        """``f_fuse = f_vox + f_img`` for every voxel; coordinates (and spconv index cache) unchanged.

        ``query_add``: MSDFF only, ``(N, C)`` added to the query (the authors' MSSF-PP adds the BEV
        feature of the voxel's pillar to the initialised query); ``None`` for the paper's query.
        """
        return self._fuse(voxels, inputs, query_add)[0]

    def _fuse(self, voxels: SparseVoxels, inputs: FusionInputs,
              query_add: Optional[torch.Tensor]) -> Tuple[SparseVoxels, CentroidProjection]:
        if query_add is not None and not isinstance(self.fusion, MSDFF):
            raise MSSFError("query_add: only an MSDFF fusion takes a query; got query_add with SFF")
        f_vox = voxels.features
        c = f_vox.shape[1]
        if c != self.out_channels:
            arg = "out_channels" if isinstance(self.fusion, SFF) else "embed_dim"
            where = ("the downsample's output" if self.downsample is not None else
                     "the residual blocks' output" if self.blocks is not None and self.position == "after_residual"
                     else "x.features")
            raise MSSFError(
                f"x: expected voxel features with {self.out_channels} channels at the fusion step "
                f"({type(self.fusion).__name__} {arg}={self.out_channels}), got {c} ({where}); build the "
                f"{type(self.fusion).__name__} with {arg}={c} (the stage's channels)"
            )
        # The dtype rule (docs/conventions.md): voxel features are read in the fusion's parameter dtype
        # (float64 into a float32 block is refused) and f_fuse comes out in it.
        out = self.fusion.linear if isinstance(self.fusion, SFF) else self.fusion.output_proj
        dtype = out.weight.dtype
        f_vox = to_module_dtype(f_vox, "x.features", dtype, "FusionBlock")
        projection = self.projector(
            voxels, inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size,
            inputs.points_to_sensor,
        )
        if isinstance(self.fusion, SFF):
            f_img = self.fusion(inputs.image_features, projection)
        else:
            if self.query_init is not None:
                if self.query_init.voxel_channels != c:
                    raise MSSFError(
                        f"query_init: expected voxel_channels={c} (voxel features), "
                        f"got {self.query_init.voxel_channels}"
                    )
                # Checked here, before level 0 is sampled for the query: a wrong level would otherwise be
                # reported under QueryInit's internal name f_img0.
                check_image_features(inputs.image_features, "inputs.image_features",
                                     num_levels=self.fusion.num_levels,
                                     channels=[self.fusion.value_channels] * self.fusion.num_levels,
                                     channels_name="MSDFF value_channels")
                qi = self.query_init
                f_img0 = sample_at_projection(inputs.image_features[0], projection, align_corners=qi.align_corners)
                geo = torch.float64 if dtype == torch.float64 else torch.float32  # positions: float32 or better
                where = projection.centroid.to(geo) if qi.position == "centroid" else voxels.voxel_centers(dtype=geo)
                query = qi(f_vox, f_img0, where)
            else:
                query = f_vox
            if query_add is not None:
                if tuple(query_add.shape) != tuple(query.shape):
                    raise MSSFError(f"query_add: expected shape {tuple(query.shape)} (the query), "
                                    f"got {tuple(query_add.shape)}")
                query = query + to_module_dtype(query_add, "query_add", dtype, "FusionBlock")
            f_img = self.fusion(query, inputs.image_features, projection)
        return voxels.replace(features=f_vox + f_img.to(dtype)), projection

    def forward(self, x: Any, inputs: FusionInputs, return_logits: bool = False,
                query_add: Optional[torch.Tensor] = None) -> Any:
        if not isinstance(inputs, FusionInputs):
            raise MSSFError(f"inputs: expected FusionInputs, got {type(inputs).__name__}")
        if not isinstance(return_logits, bool):
            raise MSSFError(f"return_logits: expected a bool, got {return_logits!r}")
        if return_logits and self.semantic_head is None:
            raise MSSFError("return_logits: True needs a semantic_head; this FusionBlock was built without one")
        if not isinstance(x, SparseVoxels) and not _is_spconv_tensor(x):
            raise MSSFError(f"x: expected SparseVoxels or an spconv SparseConvTensor, got {type(x).__name__}")
        # Before any spconv code: what SparseVoxels.to_spconv checks, plus what the first spconv module takes.
        first = self.downsample if self.downsample is not None else (
            self.blocks if self.position == "after_residual" else None)
        if first is not None or not isinstance(x, SparseVoxels):
            check_sparse_tensor(x, "x", first, "downsample" if self.downsample is not None else "blocks")
        if not isinstance(x, SparseVoxels):
            check_indices_in_shape(x.indices, x.spatial_shape)
        if isinstance(x.batch_size, int):  # (an spconv tensor may hold a 0-d tensor: not read here)
            check_agreement(camera_batch_entries(inputs), "batch size", ("x.batch_size", x.batch_size))
        if isinstance(x, SparseVoxels):
            grid = self._check_voxels_grid(x)
            in_stride = x.stride
        else:
            if self.grid is None:
                raise MSSFError(
                    "x: an spconv SparseConvTensor carries no metric grid; construct FusionBlock with "
                    "grid=VoxelGrid(voxel_size, point_cloud_range) (or pass SparseVoxels)"
                )
            grid = self.grid
            in_stride = grid.stride_of(x.spatial_shape, "x.spatial_shape")
        out_stride = self.output_stride(in_stride)
        check_grid(x.spatial_shape, grid.voxel_size, grid.point_range_min, in_stride, grid.point_range_max)
        if self.query_init is not None and not getattr(self, "_query_range_warned", False) and not is_tracing():
            # (its range normalises the query positions: the grid's; once per block, not every step)
            msg = query_range_mismatch(self.query_init.point_cloud_range, x.spatial_shape, grid.voxel_size,
                                       grid.point_range_min, in_stride)
            if msg is not None:
                self._query_range_warned = True
                warnings.warn(msg, MSSFGeometryWarning, stacklevel=4)  # (past nn.Module.__call__)

        def as_spconv(t: Any) -> Any:
            return t.to_spconv() if isinstance(t, SparseVoxels) else t

        def as_voxels(t: Any) -> SparseVoxels:
            # from_spconv shares features, indices and the index cache of t (no copy).
            return t if isinstance(t, SparseVoxels) else SparseVoxels.from_spconv(t, grid, stride=out_stride)

        head_read: list = []
        fused: list = []  # (voxels, projection) of the fusion step: the head's centroids when it reads those voxels

        def fuse(t: Any) -> SparseVoxels:
            out, projection = self._fuse(as_voxels(t), inputs, query_add)
            fused.append((out, projection))
            return out

        def head(t: Any) -> Any:
            if self.semantic_head is None:
                return t
            v = as_voxels(t)
            weighted, _, logits = self.semantic_head(v, return_logits=True)
            head_read.append((v, logits))
            return weighted

        cur = x
        if self.downsample is not None:
            cur = self.downsample(as_spconv(cur))
        if self.position == "before_residual":
            cur = fuse(cur)
            if self.head_position == "after_fusion":
                cur = head(cur)
            if self.blocks is not None:
                check_sparse_tensor(cur, "f_fuse", self.blocks, "blocks")
                cur = self.blocks(as_spconv(cur))
            if self.head_position == "after_residual":
                cur = head(cur)
        else:
            if self.blocks is not None:
                if self.downsample is not None:
                    check_sparse_tensor(cur, "downsample(x)", self.blocks, "blocks")
                cur = self.blocks(as_spconv(cur))
            cur = head(fuse(cur))
        out = as_voxels(cur) if isinstance(x, SparseVoxels) else as_spconv(cur)
        if return_logits:
            v, logits = head_read[0]
            centroids, has_points = self._head_centroids(v, fused[0], inputs)
            return FusionBlockOutput(out, v, logits, centroids, has_points)
        return out

    def _check_voxels_grid(self, x: SparseVoxels) -> VoxelGrid:
        """The grid of a :class:`SparseVoxels` input, which must be the block's (voxel size and lower
        corner; a loose-form tensor spans its own upper corner) when the block has one."""
        if self.grid is not None and not (
                all(abs(a - b) <= 1e-6 * max(1.0, abs(b)) for a, b in zip(x.voxel_size, self.grid.voxel_size))
                and all(abs(a - b) <= 1e-6 * max(1.0, abs(b)) for a, b in zip(x.point_range_min,
                                                                               self.grid.point_range_min))):
            raise MSSFError(
                f"x.grid: expected the block's grid (voxel_size {self.grid.voxel_size}, point_range_min "
                f"{self.grid.point_range_min}), got voxel_size {x.voxel_size}, point_range_min {x.point_range_min}")
        return x.grid if self.grid is None else self.grid

    def _head_centroids(self, v: SparseVoxels, fused: Tuple[SparseVoxels, CentroidProjection],
                        inputs: FusionInputs) -> Tuple[torch.Tensor, torch.Tensor]:
        """Centroids of the voxels the head read: the fusion's own where they are its voxels (the same
        rows: submanifold residual blocks keep the index tensor), else computed from the points."""
        f_voxels, projection = fused
        if v.coords is f_voxels.coords:
            return projection.centroid, projection.has_points
        return voxel_centroids(inputs.points, inputs.points_batch, v.coords, v.spatial_shape, v.batch_size,
                               v.voxel_size, v.point_range_min, v.stride, self.projector.point_range_max)

    def extra_repr(self) -> str:
        return (
            f"grid={self.grid}, position={self.position!r}, head_position={self.head_position!r}, "
            f"downsample_stride={self.downsample_stride}"
        )
