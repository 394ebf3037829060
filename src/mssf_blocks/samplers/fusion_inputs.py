"""``FusionInputs``: the camera side of a fusion block (image levels, projection matrices, raw points).

Built once per batch and handed to every fusion block; its checks (batch sizes and cameras that agree,
level shapes, the image size against level 0's aspect, ``(P, 3)`` points) run once, here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

from torch import Tensor

from mssf_blocks.checks.tensors import check_points
from mssf_blocks.checks.arguments import check_image_size
from mssf_blocks.checks.image_features import check_image_features
from mssf_blocks.checks.geometry import check_level_sizes
from mssf_blocks.functional.geometry import normalize_lidar2img
from mssf_blocks.static_path import register_pytree
from mssf_blocks.checks.agreement import check_input_agreement

__all__ = ["FusionInputs", "check_input_agreement"]


@dataclass(frozen=True, eq=False)
class FusionInputs:
    """The camera side of a fusion block: image features plus what projection needs.

    Attributes:
        image_features: ``L`` levels, each ``(B, C_l, H_l, W_l)`` or ``(B, V, C_l, H_l, W_l)``.
        lidar2img: ``(B, V, 3, 4)`` (or ``(B, 3, 4)`` for one camera) sensor-to-pixel matrices.
        image_size: ``(H, W)`` of the image the features were computed from.
        points: ``(P, 3)`` raw x, y, z (for voxel centroids); other columns are refused (slice them
            off: ``pts[:, :3]``, or ``pts[:, 1:4]`` for OpenPCDet's ``(b, x, y, z, ...)``).
        points_batch: ``(P,)`` integer batch index of every point.
        points_to_sensor: optional ``(B, 4, 4)`` inverse of the point-cloud augmentation.

    Raises:
        MSSFError: levels with different batch sizes or cameras, ``V`` not matching ``lidar2img``, a
            level that is not 4-d or 5-d, a bad ``image_size`` (also one whose aspect disagrees with
            level 0's by more than one level-0 pixel, e.g. a swapped ``(W, H)``), ``points`` that are not
            ``(P, 3)``.
    """

    image_features: Sequence[Tensor]
    lidar2img: Tensor
    image_size: Tuple[int, int]
    points: Tensor
    points_batch: Tensor
    points_to_sensor: Optional[Tensor] = None

    def __post_init__(self) -> None:
        l2i = normalize_lidar2img(self.lidar2img)
        check_input_agreement(self.image_features, self.lidar2img, l2i, self.points_to_sensor)
        levels = check_image_features(
            self.image_features, "image_features", batch_size=l2i.shape[0], num_cameras=l2i.shape[1]
        )
        # Every level is the image over a stride, finest first; a channels-last level is named.
        check_level_sizes(levels, self.image_size)
        # The levels know the image's aspect: a swapped (W, H) would silently move every sampling spot.
        h, w = check_image_size(self.image_size, levels[0].shape[-2:])
        object.__setattr__(self, "image_size", (h, w))
        object.__setattr__(self, "image_features", tuple(self.image_features))
        check_points(self.points, self.points_batch, exact_xyz=True)

    @property
    def batch_size(self) -> int:
        return int(self.image_features[0].shape[0])

    @property
    def num_cameras(self) -> int:
        return int(normalize_lidar2img(self.lidar2img).shape[1])


# torch.export / ONNX: the tensors are graph inputs; image_size is the graph's fixed context
register_pytree(FusionInputs, ("image_features", "lidar2img", "points", "points_batch", "points_to_sensor"),
                ("image_size",))
