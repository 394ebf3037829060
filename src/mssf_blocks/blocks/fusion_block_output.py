"""``FusionBlockOutput``: what ``FusionBlock(..., return_logits=True)`` returns."""

from __future__ import annotations

from typing import Any

from torch import Tensor

__all__ = ["FusionBlockOutput"]


class FusionBlockOutput(tuple):
    """``(voxels, head_voxels, logits)`` (unpacks as three), plus what the head's loss needs.

    Attributes:
        voxels: the block's output (the type of its input: ``SparseVoxels`` or an spconv tensor).
        head_voxels: the :class:`~mssf_blocks.SparseVoxels` the semantic-guided head read (``N`` rows).
        logits: ``(N,)`` the head's logits (for :meth:`~mssf_blocks.SemanticGuidedHead.loss`).
        centroids: ``(N, 3)`` metric ``(x, y, z)`` centroid of each of those voxels (its centre where it
            holds no point), the ones the fusion projected: the head's labels need no second projection,
            ``voxel_foreground_labels(out.centroids, out.batch_index, gt_boxes)``.
        has_points: ``(N,)`` which of those voxels hold raw points.
        batch_index: ``(N,)`` int64 sample of each row (``head_voxels.batch_index``).
    """

    centroids: Tensor
    has_points: Tensor

    def __new__(cls, voxels: Any, head_voxels: Any, logits: Tensor, centroids: Tensor,
                has_points: Tensor) -> "FusionBlockOutput":
        self = super().__new__(cls, (voxels, head_voxels, logits))
        self.centroids, self.has_points = centroids, has_points
        return self

    @property
    def voxels(self) -> Any:
        return self[0]

    @property
    def head_voxels(self) -> Any:
        return self[1]

    @property
    def logits(self) -> Tensor:
        return self[2]

    @property
    def batch_index(self) -> Tensor:
        return self[1].batch_index

    def __repr__(self) -> str:
        return (f"FusionBlockOutput(voxels={type(self[0]).__name__}, head_voxels={self[1]!r}, "
                f"logits={tuple(self[2].shape)}, centroids={tuple(self.centroids.shape)})")
