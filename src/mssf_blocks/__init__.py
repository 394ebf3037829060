"""mssf-blocks: plug-and-play radar-camera fusion blocks from the MSSF paper.

Core dependencies are torch, numpy and einops; spconv, matplotlib and tqdm are optional extras.
The data structures: :class:`VoxelGrid` (voxel size + point-cloud range, one per model) and
:class:`SparseVoxels` (the sparse tensor). The blocks: :class:`FusionBlock` and :class:`PillarFusionStage`
(``blocks/``), built from the image samplers :class:`SFF` and :class:`MSDFF` with :class:`QueryInit`
(``samplers/``), :class:`VoxelCentroidProjector` (``geometry/``), :class:`SemanticGuidedHead` (``heads/``),
:class:`PillarLift` with :class:`HeightEmbedding` (``lift/``); pure functions in :mod:`mssf_blocks.functional`;
every input check in :mod:`mssf_blocks.checks`; feature-blurring analysis in :mod:`mssf_blocks.diagnostics`;
the authors' checkpoints in :mod:`mssf_blocks.weights`; test helpers in :mod:`mssf_blocks.testing`.
``docs/architecture.md`` maps the layout.
"""

from mssf_blocks._version import __version__
from mssf_blocks.blocks import FusionBlock, FusionBlockOutput, PillarFusionStage
from mssf_blocks.errors import MSSFError, MSSFGeometryWarning
from mssf_blocks.geometry import (
    CentroidProjection,
    VoxelCentroidProjector,
    apply_image_augmentation,
    augmentation_matrix,
    image_augmentation_matrix,
)
from mssf_blocks.heads import SemanticGuidedHead, points_in_boxes, sigmoid_focal_loss, voxel_foreground_labels
from mssf_blocks.lift import HeightEmbedding, PillarLift
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.static_path import static_path
from mssf_blocks.voxel_grid import VoxelGrid

__all__ = [
    "__version__",
    "MSSFError",
    "MSSFGeometryWarning",
    "VoxelGrid",
    "SparseVoxels",
    "VoxelCentroidProjector",
    "CentroidProjection",
    "augmentation_matrix",
    "SFF",
    "MSDFF",
    "QueryInit",
    "FusionInputs",
    "FusionBlock",
    "FusionBlockOutput",
    "SemanticGuidedHead",
    "sigmoid_focal_loss",
    "points_in_boxes",
    "voxel_foreground_labels",
    "HeightEmbedding",
    "PillarLift",
    "PillarFusionStage",
    "static_path",
    "image_augmentation_matrix",
    "apply_image_augmentation",
]
