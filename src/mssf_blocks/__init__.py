"""mssf-blocks: plug-and-play radar-camera fusion blocks from the MSSF paper.

Core dependencies are torch, numpy and einops; spconv, matplotlib and tqdm are optional extras.
"""

from ._version import __version__
from .errors import MSSFError
from .geometry import CentroidProjection, VoxelCentroidProjector, augmentation_matrix
from .sparse import SparseVoxels

__all__ = [
    "__version__",
    "MSSFError",
    "SparseVoxels",
    "VoxelCentroidProjector",
    "CentroidProjection",
    "augmentation_matrix",
]
