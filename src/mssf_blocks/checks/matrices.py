"""Checks of transform matrices: ``points_to_sensor`` (the inverse of the point augmentation) and the
4 x 4 affines a framework adapter reads."""

from __future__ import annotations

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_finite, check_floating, check_shape, value_check
from mssf_blocks.errors import MSSFError


def check_points_to_sensor_matrix(points_to_sensor: Tensor, batch_size: int) -> Tensor:
    """``(B, 4, 4)`` finite, floating, affine and invertible (the inverse of the point augmentation)."""
    check_shape(points_to_sensor, "points_to_sensor", (batch_size, 4, 4))
    check_floating(points_to_sensor, "points_to_sensor")
    check_finite(points_to_sensor, "points_to_sensor")
    return check_affine_invertible(points_to_sensor)


@value_check
def check_affine_invertible(points_to_sensor: Tensor) -> Tensor:
    m = points_to_sensor.detach().double()
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m.dtype, device=m.device)
    if not torch.allclose(m[:, 3], last.expand(m.shape[0], 4), atol=1e-9):
        raise MSSFError(
            "points_to_sensor: expected affine 4x4 matrices with last row (0, 0, 0, 1), "
            f"got last rows {m[:, 3].tolist()}"
        )
    lin = m[:, :3, :3]
    det = torch.linalg.det(lin).abs()
    scale = lin.abs().amax(dim=(1, 2)).clamp(min=1e-300) ** 3
    bad = (det <= 1e-12 * scale).nonzero().flatten().tolist()
    if bad:
        raise MSSFError(
            f"points_to_sensor: expected invertible augmentation matrices, got singular matrices for "
            f"samples {bad} (|det| = {[float(det[i]) for i in bad]})"
        )
    return points_to_sensor


def check_affine_4x4(m: Tensor, name: str) -> Tensor:
    """``m`` is ``(..., 4, 4)`` with last row ``(0, 0, 0, 1)`` and an invertible linear part."""
    last = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=m.dtype)
    if not torch.allclose(m[..., 3, :], last.expand_as(m[..., 3, :]), atol=1e-9):
        raise MSSFError(f"{name}: expected affine 4x4 matrices with last row (0, 0, 0, 1), got {m[..., 3, :].tolist()}")
    det = torch.linalg.det(m[..., :3, :3])
    if bool((det.abs() < 1e-12).any()):
        raise MSSFError(f"{name}: expected invertible matrices, got determinant(s) {det.tolist()}")
    return m
