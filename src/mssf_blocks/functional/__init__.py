"""Pure functions under every module (no parameters, no state)."""

from .geometry import (
    Projection,
    normalize_lidar2img,
    project_points,
    voxel_centers,
    voxel_centroids,
    voxel_centroids_reference,
)

__all__ = [
    "Projection",
    "normalize_lidar2img",
    "project_points",
    "voxel_centers",
    "voxel_centroids",
    "voxel_centroids_reference",
]
