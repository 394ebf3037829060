"""mssf-blocks: plug-and-play radar-camera fusion blocks from the MSSF paper.

Core dependencies are torch, numpy and einops; spconv, matplotlib and tqdm are optional extras.
Modules: :class:`SparseVoxels` (the sparse tensor), :class:`VoxelCentroidProjector`, the image samplers
:class:`SFF` and :class:`MSDFF` with :class:`QueryInit`, :class:`FusionBlock`, :class:`SemanticGuidedHead`,
:class:`PillarLift` with :class:`HeightEmbedding` (and :class:`PillarFusionStage`); pure functions in :mod:`mssf_blocks.functional`;
feature-blurring analysis in :mod:`mssf_blocks.diagnostics`; test helpers in :mod:`mssf_blocks.testing`.
"""

from ._version import __version__
from .blocks import FusionBlock
from .deploy import static_path
from .errors import MSSFError
from .fusion import MSDFF, SFF, FusionInputs, QueryInit
from .geometry import CentroidProjection, VoxelCentroidProjector, augmentation_matrix
from .geometry import apply_image_augmentation, image_augmentation_matrix
from .heads import SemanticGuidedHead, points_in_boxes, sigmoid_focal_loss, voxel_foreground_labels
from .lift import HeightEmbedding, PillarLift
from .pillar_stage import PillarFusionStage
from .sparse import SparseVoxels

__all__ = [
    "__version__",
    "MSSFError",
    "SparseVoxels",
    "VoxelCentroidProjector",
    "CentroidProjection",
    "augmentation_matrix",
    "SFF",
    "MSDFF",
    "QueryInit",
    "FusionInputs",
    "FusionBlock",
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
