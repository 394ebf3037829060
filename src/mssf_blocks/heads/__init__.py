"""The semantic-guided head (paper Sec. III-D): :class:`SemanticGuidedHead`; its loss and labels are pure
functions in :mod:`mssf_blocks.functional.heads` (re-exported here)."""

from mssf_blocks.functional.heads import points_in_boxes, sigmoid_focal_loss, voxel_foreground_labels
from mssf_blocks.heads.semantic_guided_head import SemanticGuidedHead

__all__ = ["SemanticGuidedHead", "points_in_boxes", "sigmoid_focal_loss", "voxel_foreground_labels"]
