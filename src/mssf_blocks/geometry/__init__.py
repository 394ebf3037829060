"""Geometry: the voxel grid, voxel centroids projected into the cameras, and the augmentation matrices.

* :class:`VoxelGrid` - ``voxel_size`` + ``point_cloud_range`` (x, y, z), the one grid description every
  block takes (re-exported: it lives in ``mssf_blocks/voxel_grid.py`` beside ``SparseVoxels``, which holds one);
* :class:`VoxelCentroidProjector` and its result :class:`CentroidProjection` (``voxel_centroid_projector.py``);
* :func:`augmentation_matrix`, :func:`image_augmentation_matrix`, :func:`apply_image_augmentation`
  (``augmentation.py``).
"""

from mssf_blocks.geometry.augmentation import apply_image_augmentation, augmentation_matrix, image_augmentation_matrix
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection, VoxelCentroidProjector
from mssf_blocks.voxel_grid import VoxelGrid

__all__ = [
    "VoxelGrid", "VoxelCentroidProjector", "CentroidProjection", "augmentation_matrix",
    "image_augmentation_matrix", "apply_image_augmentation",
]
