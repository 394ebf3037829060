"""Box encoding and decoding for anchor-based and centre-based detection heads.

Boxes are ``(x, y, z, dx, dy, dz, yaw)`` in the sensor frame, ``z`` the box centre, ``yaw`` about +z and
``dx`` along the heading (the library-wide convention).

* :func:`encode_residual` / :func:`decode_residual`: the SECOND / OpenPCDet ``ResidualCoder``. With the
  anchor's BEV diagonal ``d = sqrt(dx_a^2 + dy_a^2)``::

      t_x = (x_g - x_a) / d     t_y = (y_g - y_a) / d     t_z = (z_g - z_a) / dz_a
      t_dx = log(dx_g / dx_a)   t_dy = log(dy_g / dy_a)   t_dz = log(dz_g / dz_a)
      t_yaw = yaw_g - yaw_a                         (raw-angle residual, code size 7)
      (cos yaw_g - cos yaw_a, sin yaw_g - sin yaw_a) (``encode_angle_by_sincos=True``, code size 8)

  Both boxes use the centre ``z`` (as OpenPCDet; the original SECOND used the bottom face, which only
  shifts ``t_z`` by a constant when the heights are equal).
* :func:`encode_center` / :func:`decode_center`: CenterPoint regression targets on a BEV cell grid:
  sub-cell offset of the centre from the integer cell index, centre ``z``, log sizes and
  ``(sin yaw, cos yaw)`` (code size 8).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.errors import MSSFError

__all__ = [
    "limit_period",
    "encode_residual",
    "decode_residual",
    "residual_code_size",
    "encode_center",
    "decode_center",
    "CENTER_CODE_SIZE",
]

#: Size of the centre-head regression code ``(off_x, off_y, z, log dx, log dy, log dz, sin, cos)``.
CENTER_CODE_SIZE = 8


def limit_period(angle: Tensor, offset: float = 0.5, period: float = 2 * math.pi) -> Tensor:
    """Wrap ``angle`` into ``[-offset * period, (1 - offset) * period)``.

    ``offset=0.5, period=2*pi`` gives ``[-pi, pi)``; ``offset=0, period=pi`` gives ``[0, pi)``.
    """
    return angle - torch.floor(angle / period + offset) * period


def residual_code_size(encode_angle_by_sincos: bool = False) -> int:
    """7 for the raw-angle residual, 8 with the ``(cos, sin)`` residual."""
    return 8 if encode_angle_by_sincos else 7


def _check_boxes(x: Tensor, name: str, last: int) -> Tensor:
    check_floating(x, name)
    if x.dim() < 1 or x.shape[-1] != last:
        raise MSSFError(f"{name}: expected shape (..., {last}), got shape {tuple(x.shape)}")
    return x


def encode_residual(boxes: Tensor, anchors: Tensor, encode_angle_by_sincos: bool = False) -> Tensor:
    """Residual code of ground-truth ``boxes`` relative to ``anchors`` (SECOND / OpenPCDet).

    Args:
        boxes: ``(..., 7)`` target boxes.
        anchors: ``(..., 7)`` anchors, broadcastable against ``boxes``; positive sizes.
        encode_angle_by_sincos: encode the yaw as ``(cos g - cos a, sin g - sin a)`` instead of ``g - a``.

    Returns:
        ``(..., 7)`` or ``(..., 8)`` codes ``(t_x, t_y, t_z, t_dx, t_dy, t_dz, t_yaw[, t_sin])``.
    """
    _check_boxes(boxes, "boxes", 7)
    _check_boxes(anchors, "anchors", 7)
    xa, ya, za, dxa, dya, dza, ra = torch.unbind(anchors, dim=-1)
    xg, yg, zg, dxg, dyg, dzg, rg = torch.unbind(boxes, dim=-1)
    diagonal = torch.sqrt(dxa**2 + dya**2)
    codes = [
        (xg - xa) / diagonal,
        (yg - ya) / diagonal,
        (zg - za) / dza,
        torch.log(dxg / dxa),
        torch.log(dyg / dya),
        torch.log(dzg / dza),
    ]
    if encode_angle_by_sincos:
        codes += [torch.cos(rg) - torch.cos(ra), torch.sin(rg) - torch.sin(ra)]
    else:
        codes += [rg - ra]
    return torch.stack(codes, dim=-1)


def decode_residual(codes: Tensor, anchors: Tensor, encode_angle_by_sincos: bool = False) -> Tensor:
    """Inverse of :func:`encode_residual`.

    Args:
        codes: ``(..., 7)`` (or ``(..., 8)`` with ``encode_angle_by_sincos``) residuals.
        anchors: ``(..., 7)`` anchors, broadcastable against ``codes``.
        encode_angle_by_sincos: as in :func:`encode_residual`; the yaw is recovered with ``atan2`` and lies
            in ``(-pi, pi]``, the raw residual returns ``t_yaw + yaw_a`` unwrapped.

    Returns:
        ``(..., 7)`` boxes.
    """
    _check_boxes(codes, "codes", residual_code_size(encode_angle_by_sincos))
    _check_boxes(anchors, "anchors", 7)
    xa, ya, za, dxa, dya, dza, ra = torch.unbind(anchors, dim=-1)
    parts = torch.unbind(codes, dim=-1)
    xt, yt, zt, dxt, dyt, dzt = parts[:6]
    diagonal = torch.sqrt(dxa**2 + dya**2)
    if encode_angle_by_sincos:
        yaw = torch.atan2(parts[7] + torch.sin(ra), parts[6] + torch.cos(ra))
    else:
        yaw = parts[6] + ra
    return torch.stack(
        [
            xt * diagonal + xa,
            yt * diagonal + ya,
            zt * dza + za,
            torch.exp(dxt) * dxa,
            torch.exp(dyt) * dya,
            torch.exp(dzt) * dza,
            yaw,
        ],
        dim=-1,
    )


def encode_center(boxes: Tensor, cell_index: Tensor, cell_size: tuple, origin: tuple) -> Tensor:
    """CenterPoint regression targets of ``boxes`` at their assigned BEV cells.

    The continuous cell coordinate of a point is ``u = (x - x_min) / cell_x`` (columns) and
    ``v = (y - y_min) / cell_y`` (rows); cell ``(col, row)`` covers ``[col, col+1) x [row, row+1)``.

    Args:
        boxes: ``(G, 7)`` boxes.
        cell_index: ``(G, 2)`` integer ``(col, row)`` of the cell (or voxel) each box is assigned to.
        cell_size: ``(cell_x, cell_y)`` in metres.
        origin: ``(x_min, y_min)`` in metres.

    Returns:
        ``(G, 8)``: ``(u - col, v - row, z, log dx, log dy, log dz, sin yaw, cos yaw)``.
    """
    dims: dict = {}
    check_shape(boxes, "boxes", ("G", 7), dims)
    check_shape(cell_index, "cell_index", ("G", 2), dims)
    check_floating(boxes, "boxes")
    u = (boxes[:, 0] - origin[0]) / cell_size[0]
    v = (boxes[:, 1] - origin[1]) / cell_size[1]
    cell_index = cell_index.to(boxes.dtype)
    return torch.stack(
        [
            u - cell_index[:, 0],
            v - cell_index[:, 1],
            boxes[:, 2],
            torch.log(boxes[:, 3]),
            torch.log(boxes[:, 4]),
            torch.log(boxes[:, 5]),
            torch.sin(boxes[:, 6]),
            torch.cos(boxes[:, 6]),
        ],
        dim=-1,
    )


def decode_center(codes: Tensor, cell_index: Tensor, cell_size: tuple, origin: tuple) -> Tensor:
    """Inverse of :func:`encode_center` (yaw from ``atan2(sin, cos)``, in ``(-pi, pi]``).

    Args:
        codes: ``(..., 8)`` regression outputs.
        cell_index: ``(..., 2)`` integer ``(col, row)`` of the cells the codes were read at.
        cell_size: ``(cell_x, cell_y)`` in metres.
        origin: ``(x_min, y_min)`` in metres.

    Returns:
        ``(..., 7)`` boxes.
    """
    _check_boxes(codes, "codes", CENTER_CODE_SIZE)
    if cell_index.shape != codes.shape[:-1] + (2,):
        raise MSSFError(
            f"cell_index: expected shape {tuple(codes.shape[:-1]) + (2,)}, got shape {tuple(cell_index.shape)}"
        )
    cell_index = cell_index.to(codes.dtype)
    x = (cell_index[..., 0] + codes[..., 0]) * cell_size[0] + origin[0]
    y = (cell_index[..., 1] + codes[..., 1]) * cell_size[1] + origin[1]
    size = torch.exp(codes[..., 3:6])
    yaw = torch.atan2(codes[..., 6], codes[..., 7])
    return torch.cat([x[..., None], y[..., None], codes[..., 2:3], size, yaw[..., None]], dim=-1)
