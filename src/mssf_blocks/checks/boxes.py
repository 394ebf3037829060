"""Checks of 3D boxes ``(M, 7)`` ``(x, y, z, dx, dy, dz, yaw)`` and of the box arguments of the semantic head's
labels (origin, margins): :func:`~mssf_blocks.functional.heads.points_in_boxes`, ``voxel_foreground_labels``."""

from __future__ import annotations

from torch import Tensor

from mssf_blocks.checks.tensors import check_finite, check_floating, check_shape
from mssf_blocks.errors import MSSFError

#: where a box's z sits: its centre (mmdetection3d's LiDAR boxes after conversion) or its bottom face
ORIGINS = ("center", "bottom")


def check_boxes(boxes: Tensor, name: str) -> Tensor:
    check_shape(boxes, name, ("G", None))
    if boxes.shape[1] < 7:
        raise MSSFError(
            f"{name}: expected shape (G, 7) boxes (x, y, z, dx, dy, dz, yaw) (extra columns are ignored), "
            f"got shape {tuple(boxes.shape)}"
        )
    check_floating(boxes, name)
    check_finite(boxes[:, :7], name)
    if boxes.shape[0] and bool((boxes[:, 3:6] < 0).any()):
        raise MSSFError(f"{name}: expected non-negative sizes dx, dy, dz, got min {float(boxes[:, 3:6].min())}")
    return boxes


def check_origin(origin: str) -> str:
    if origin not in ORIGINS:
        raise MSSFError(f"origin: expected 'center' or 'bottom' (z of the box centre or bottom face), got {origin!r}")
    return origin


def check_margin(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0 <= value < float("inf")):
        raise MSSFError(f"{name}: expected a finite non-negative float (metres), got {value!r}")
    return float(value)
