"""Deployment graph of the pure-torch MSSF-PointPillars: voxelised inputs -> head outputs (exportable).

A deployed detector voxelises its point cloud outside the network graph (``unique`` / hashing has a
data-dependent output size; TensorRT pipelines do it in a pre-processing kernel). :class:`PointPillarsGraph`
takes the result of :meth:`PointPillarsBackbone.voxelize` as flat tensors (the layout below) and runs the
rest of :class:`~mssf_examples.models.detectors.MSSFDetector` - pillar feature net, 2D blocks, pillar lifts,
fusion blocks (centroids, projection, SFF / MSDFF, QueryInit), semantic-guided head, anchor head - with
the blocks' static-shape path, so ``torch.export`` / ``torch.onnx.export(dynamo=True)`` capture one graph
whose point, pillar and voxel counts are dynamic axes.

Flat inputs (:func:`graph_inputs` builds them from a batch; ``P`` points, ``P_k`` of them inside the
pillar range, ``N_p`` pillars, ``N_i`` lift voxels of fusion block ``i``):

* ``points (P, C)``, ``points_batch (P,)`` int64 - every point (the fusion blocks' centroids use them);
* ``pillar_keep (P_k,)`` int64 - the rows of ``points`` inside the pillar grid;
* ``pillar_point (P_k,)`` int64 - the pillar row of each of them;
* ``pillar_coords (N_p, 4)`` int32 ``(b, z, y, x)``;
* ``lift_coords``: one ``(N_i, 4)`` int32 tensor per fusion block, at its BEV stride;
* ``images (B, V, 3, H, W)`` (image branch) or the precomputed levels ``(B, V, C, H_l, W_l)``;
* ``lidar2img (B, V, 3, 4)``.

Outputs: the anchor head's ``dict(cls, box[, dir])`` (decoding and NMS stay outside the graph).
spconv detectors (SECOND, CenterPoint, VoxelNeXt) are not exportable (spconv has no ONNX / export
support); export their fusion blocks (``docs/deployment.md``).
"""

from __future__ import annotations

from typing import Dict, List, Sequence, Tuple, Union

import torch
from torch import Tensor, nn

from mssf_blocks.torch_versions import require
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import FusionInputs
from mssf_blocks.sparse_voxels import SparseVoxels

from ..data.batch import RadarCameraBatch
from .voxelize import Voxelization

__all__ = ["PointPillarsGraph", "graph_inputs", "graph_dynamic_shapes", "input_names"]


class PointPillarsGraph(nn.Module):
    """The exportable part of an MSSF-PointPillars :class:`MSSFDetector` (shares its modules).

    Args:
        detector: a ``"pointpillars"`` detector (any number of fusion blocks, SFF or MSDFF, image branch or
            precomputed features).
        image_size: ``(H, W)`` the projection refers to (the image size of the batches it will run on).
    """

    def __init__(self, detector: nn.Module, image_size: Sequence[int]) -> None:
        super().__init__()
        if getattr(detector, "name", None) != "pointpillars":
            raise MSSFError(
                f"detector: expected the pure-torch 'pointpillars' detector (spconv networks cannot be exported), "
                f"got {getattr(detector, 'name', type(detector).__name__)!r}"
            )
        self.detector = detector
        self.image_size = (int(image_size[0]), int(image_size[1]))

    def forward(self, points: Tensor, points_batch: Tensor, pillar_keep: Tensor, pillar_point: Tensor,
                pillar_coords: Tensor, lift_coords: List[Tensor], image_input: Union[Tensor, List[Tensor]],
                lidar2img: Tensor) -> Dict[str, Tensor]:
        det, bb = self.detector, self.detector.backbone
        b = lidar2img.shape[0]
        # the pillars' Voxelization, rebuilt from the assignment with static shapes (mean of the kept points)
        kept = points.index_select(0, pillar_keep)
        n_p = pillar_coords.shape[0]
        counts = kept.new_zeros(n_p).index_add(0, pillar_point, kept.new_ones(kept.shape[0]))
        means = kept.new_zeros(n_p, kept.shape[1]).index_add(0, pillar_point, kept) / counts.clamp(min=1)[:, None]
        pillars = Voxelization(features=means, coords=pillar_coords, point_voxel=pillar_point, keep=pillar_keep,
                               num_points=counts)
        g = bb.lift_grid
        d, h, w = g.spatial_shape
        lifts = []
        for i, coords in enumerate(lift_coords):
            s = bb.strides[i]
            lifts.append(SparseVoxels(coords.new_zeros(coords.shape[0], 1, dtype=points.dtype), coords,
                                      (d, -(-h // s), -(-w // s)), b, voxel_size=g.voxel_size,
                                      point_range_min=g.point_range_min, stride=(1, s, s)))
        fusion_inputs = None
        if det.num_fusion_blocks:
            feats = det.image_branch(image_input) if det.image_branch is not None else list(image_input)
            fusion_inputs = FusionInputs(feats, lidar2img, self.image_size, points[:, :3], points_batch)
        out = bb(points, points_batch, b, fusion_inputs, voxelization=(pillars, lifts))
        return det.head(out.bev)


def graph_inputs(detector: nn.Module, batch: RadarCameraBatch) -> Tuple:
    """The flat inputs of :class:`PointPillarsGraph` for ``batch`` (voxelised eagerly, as a deployment would)."""
    pts, pb = batch.flat_points()
    pillars, lifts = detector.backbone.voxelize(pts, pb, batch.batch_size)
    image_input = batch.images if detector.image_branch is not None else list(batch.image_features or [])
    return (pts, pb, pillars.keep.nonzero().squeeze(1), pillars.point_voxel, pillars.coords,
            [v.coords for v in lifts], image_input, batch.lidar2img)


def graph_dynamic_shapes(detector: nn.Module, num_image_inputs: int = 1) -> Tuple:
    """``dynamic_shapes`` for ``torch.export`` / ``torch.onnx.export`` matching :func:`graph_inputs`:
    the point, kept-point, pillar and lift-voxel counts are dynamic; batch, cameras and image sizes static."""
    require("export_dynamic_shapes", "graph_dynamic_shapes")  # (torch-version dependent: mssf_blocks.torch_versions)
    from torch.export import Dim

    p, pk, n_p = Dim("P", min=2), Dim("P_k", min=2), Dim("N_p", min=2)
    lifts = [{0: Dim(f"N_{i}", min=2)} for i in range(detector.num_fusion_blocks)]
    image = None if detector.image_branch is not None else [None] * num_image_inputs
    return ({0: p}, {0: p}, {0: pk}, {0: pk}, {0: n_p}, lifts, image, None)


def input_names(detector: nn.Module, num_image_inputs: int = 1) -> List[str]:
    """Names of the flat graph inputs, in order (the ONNX model's inputs when exported with them)."""
    names = ["points", "points_batch", "pillar_keep", "pillar_point", "pillar_coords"]
    names += [f"lift_coords_{i}" for i in range(detector.num_fusion_blocks)]
    if detector.num_fusion_blocks:
        names += ["images"] if detector.image_branch is not None else [f"image_features_{i}"
                                                                       for i in range(num_image_inputs)]
    return names + ["lidar2img"]
