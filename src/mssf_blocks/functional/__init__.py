"""Pure functions under every module (no parameters, no state)."""

from mssf_blocks.functional.geometry import (
    Projection,
    normalize_lidar2img,
    project_points,
    voxel_centers,
    voxel_centroids,
    voxel_centroids_reference,
)
from mssf_blocks.functional.heads import points_in_boxes, sigmoid_focal_loss, voxel_foreground_labels
from mssf_blocks.functional.lift import bev_shape_for, pillar_lift, voxelize_points, voxels_to_bev, voxels_to_bev_sparse
from mssf_blocks.functional.deform import deform_sample_project, ms_deform_sample, ms_deform_sample_project, ms_deform_sample_reference
from mssf_blocks.functional.sampling import bilinear_sample, camera_mean

__all__ = [
    "Projection",
    "normalize_lidar2img",
    "project_points",
    "voxel_centers",
    "voxel_centroids",
    "voxel_centroids_reference",
    "bilinear_sample",
    "camera_mean",
    "ms_deform_sample",
    "ms_deform_sample_reference",
    "ms_deform_sample_project",
    "deform_sample_project",
    "points_in_boxes",
    "sigmoid_focal_loss",
    "voxel_foreground_labels",
    "pillar_lift",
    "voxels_to_bev",
    "voxels_to_bev_sparse",
    "voxelize_points",
    "bev_shape_for",
]
