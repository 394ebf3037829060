"""The input batch every example detector takes.

A batch holds, per sample, the radar points (any number, with their per-point features), the camera
images (or their precomputed multi-scale features), the projection matrices, an optional inverse of
the point-cloud augmentation (so voxel centroids can be projected into the un-augmented images), and
the ground truth in the sensor frame (boxes ``(x, y, z, dx, dy, dz, yaw)``, z = box centre).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.errors import MSSFError

__all__ = ["RadarCameraBatch"]


@dataclass
class RadarCameraBatch:
    """One batch of radar + camera samples.

    Attributes:
        points: list of ``B`` tensors ``(P_b, C_in)``; columns 0..2 are metric ``(x, y, z)`` in the
            (possibly augmented) sensor frame, the rest are the preset's point features (e.g. RCS,
            v_r, v_rc, t for VoD). ``C_in`` must be equal across samples.
        lidar2img: ``(B, V, 3, 4)`` projection of homogeneous *un-augmented* sensor-frame points to
            ``(u*d, v*d, d)`` (OpenCV pixels of ``images``; when an image was flipped or resized, its
            pixel affine is folded in: ``A @ lidar2img``, see :mod:`mssf_examples.data.augment`).
        images: ``(B, V, 3, H, W)`` float images, or ``None`` (precomputed ``image_features``, or a
            radar-only detector).
        image_features: optional precomputed image features, a sequence of ``L`` levels, each
            ``(B, V, C_l, H_l, W_l)`` (e.g. from a frozen image branch, as in the paper).
        image_size: ``(H, W)`` of the image the features/projection refer to; inferred from ``images``
            when omitted, required with ``image_features`` alone.
        points_to_sensor: optional ``(B, 4, 4)`` inverse of the point augmentation (maps augmented
            points back to the frame ``lidar2img`` expects); ``None`` means no augmentation.
        gt_boxes: optional list of ``B`` tensors ``(G_b, 7)`` in the augmented sensor frame.
        gt_labels: optional list of ``B`` long tensors ``(G_b,)``, 0-based class indices.
    """

    points: List[Tensor]
    lidar2img: Tensor
    images: Optional[Tensor] = None
    image_features: Optional[Sequence[Tensor]] = None
    image_size: Optional[Tuple[int, int]] = None
    points_to_sensor: Optional[Tensor] = None
    gt_boxes: Optional[List[Tensor]] = None
    gt_labels: Optional[List[Tensor]] = None

    def __post_init__(self) -> None:
        if not isinstance(self.points, (list, tuple)) or len(self.points) == 0:
            raise MSSFError(f"points: expected a non-empty list of (P_b, C_in) tensors, got {type(self.points).__name__}")
        self.points = list(self.points)
        dims: dict = {}
        for i, p in enumerate(self.points):
            check_shape(p, f"points[{i}]", (None, "C_in"), dims)
            check_floating(p, f"points[{i}]")
        if dims["C_in"] < 3:
            raise MSSFError(f"points: expected at least 3 columns (x, y, z), got {dims['C_in']}")
        b = len(self.points)
        check_shape(self.lidar2img, "lidar2img", (b, None, 3, 4))
        v = int(self.lidar2img.shape[1])
        if self.images is not None:
            check_shape(self.images, "images", (b, v, 3, None, None))
            check_floating(self.images, "images")
            size = (int(self.images.shape[-2]), int(self.images.shape[-1]))
            if self.image_size is not None and tuple(self.image_size) != size:
                raise MSSFError(f"image_size: expected {size} (the size of images), got {tuple(self.image_size)}")
            self.image_size = size
        if self.image_features is not None:
            if len(self.image_features) == 0:
                raise MSSFError("image_features: expected at least one level, got an empty sequence")
            for i, f in enumerate(self.image_features):
                check_shape(f, f"image_features[{i}]", (b, v, None, None, None))
        if self.image_features is not None and self.image_size is None:
            raise MSSFError("image_size: required with image_features and no images (the size lidar2img refers to)")
        if self.image_size is not None:
            self.image_size = (int(self.image_size[0]), int(self.image_size[1]))
        if self.points_to_sensor is not None:
            check_shape(self.points_to_sensor, "points_to_sensor", (b, 4, 4))
        if (self.gt_boxes is None) != (self.gt_labels is None):
            raise MSSFError("gt_boxes / gt_labels: expected both or neither")
        if self.gt_boxes is not None:
            if len(self.gt_boxes) != b or len(self.gt_labels) != b:
                raise MSSFError(
                    f"gt_boxes / gt_labels: expected {b} entries (one per sample), "
                    f"got {len(self.gt_boxes)} / {len(self.gt_labels)}"
                )
            for i, (bx, lb) in enumerate(zip(self.gt_boxes, self.gt_labels)):
                g: dict = {}
                check_shape(bx, f"gt_boxes[{i}]", ("G", 7), g)
                check_shape(lb, f"gt_labels[{i}]", ("G",), g)
                if lb.dtype != torch.long:
                    raise MSSFError(f"gt_labels[{i}]: expected dtype torch.int64, got {lb.dtype}")

    @property
    def batch_size(self) -> int:
        return len(self.points)

    @property
    def num_cameras(self) -> int:
        return int(self.lidar2img.shape[1])

    @property
    def num_point_features(self) -> int:
        return int(self.points[0].shape[1])

    def flat_points(self) -> Tuple[Tensor, Tensor]:
        """All points concatenated: ``points (P, C_in)`` and ``points_batch (P,)`` int64."""
        pts = torch.cat(self.points, 0)
        batch = torch.cat(
            [torch.full((p.shape[0],), i, dtype=torch.long, device=p.device) for i, p in enumerate(self.points)]
        )
        return pts, batch

    def to(self, device: torch.device | str, non_blocking: bool = False) -> "RadarCameraBatch":
        """A copy with every tensor on ``device`` (``non_blocking`` copies from pinned memory overlap)."""
        return self._map(lambda x: x.to(device, non_blocking=non_blocking))

    def pin_memory(self) -> "RadarCameraBatch":
        """A copy in page-locked memory (``DataLoader(pin_memory=True)`` calls this), for fast host-to-GPU copies."""
        return self._map(lambda x: x.pin_memory())

    def _map(self, fn) -> "RadarCameraBatch":
        def move(x):
            if isinstance(x, Tensor):
                return fn(x)
            if isinstance(x, (list, tuple)):
                return [move(t) for t in x]
            return x

        return replace(self, **{f.name: move(getattr(self, f.name)) for f in fields(self)})
