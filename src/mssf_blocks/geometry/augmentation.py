"""Augmentation matrices: the point-cloud augmentation to undo (``points_to_sensor``) and the image-side
pixel affine (flip, resize, crop) applied as ``lidar2img' = A @ lidar2img``; both exact to float rounding
(``docs/conventions.md``, "Projection")."""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_floating
from mssf_blocks.checks.arguments import check_radians, check_triple
from mssf_blocks.errors import MSSFError
from mssf_blocks.checks.arguments import check_size

__all__ = ["augmentation_matrix", "image_augmentation_matrix", "apply_image_augmentation"]


def augmentation_matrix(
    flip_x: bool = False,
    flip_y: bool = False,
    rotation: float = 0.0,
    scale: float = 1.0,
    translation: Sequence[float] = (0.0, 0.0, 0.0),
    dtype: torch.dtype = torch.float64,
) -> Tensor:
    """``(4, 4)`` global point-cloud augmentation as OpenPCDet/mmdet3d apply it, in that order.

    ``p' = T + s * Rz(rotation) * F * p`` where ``F`` flips y (``flip_x``: mirror across the x axis,
    ``y -> -y``) and/or x (``flip_y``: ``x -> -x``); ``rotation`` in radians (a magnitude above ``2 pi``
    is refused: degrees). Its inverse (``torch.linalg.inv``) is the
    ``points_to_sensor`` matrix that :class:`VoxelCentroidProjector` takes.
    """
    if not scale > 0:
        raise MSSFError(f"scale: expected a positive float, got {scale!r}")
    check_radians(rotation, "rotation")
    t = check_triple(translation, "translation", float)
    f = torch.eye(4, dtype=dtype)
    if flip_x:
        f[1, 1] = -1.0
    if flip_y:
        f[0, 0] = -1.0
    c, s = math.cos(rotation), math.sin(rotation)
    r = torch.eye(4, dtype=dtype)
    r[0, 0], r[0, 1], r[1, 0], r[1, 1] = c, -s, s, c
    m = r @ f
    m[:3, :3] *= scale
    m[:3, 3] = torch.tensor(t, dtype=dtype)
    return m


def image_augmentation_matrix(
    image_size: Sequence[int],
    resize: Optional[Sequence[int]] = None,
    crop: Optional[Sequence[int]] = None,
    flip: bool = False,
    dtype: torch.dtype = torch.float64,
    corner_origin: bool = False,
) -> Tuple[Tensor, Tuple[int, int]]:
    """``(3, 3)`` pixel affine of an image resize, crop and horizontal flip (in that order), and the new size.

    OpenCV pixel convention (pixel ``i``'s centre at ``i``, its area ``[i - 0.5, i + 0.5)``):

    * resize ``(H, W) -> (H', W')`` with edges aligned (``F.interpolate(..., align_corners=False)``,
      OpenCV ``resize``): ``u -> s_x (u + 0.5) - 0.5`` with ``s_x = W' / W`` (``v`` alike);
    * crop ``(top, left, height, width)``: ``u -> u - left``, ``v -> v - top``;
    * horizontal flip of a ``W``-wide image (``torch.flip(image, [-1])``): ``u -> W - 1 - u``
      (not ``W - u``: that is the flip in corner-origin pixel coordinates).

    The projection into the augmented image is ``lidar2img' = A @ lidar2img``
    (:func:`apply_image_augmentation`), and the projector / samplers must be given the returned size.
    Other orders are products: ``A2 @ A1`` where ``A1``'s output size is ``A2``'s ``image_size``.

    Args:
        image_size: ``(H, W)`` before the augmentation.
        resize: optional ``(H', W')`` after resizing.
        crop: optional ``(top, left, height, width)`` window of the resized image (it may reach past the
            image: those pixels are padding).
        flip: mirror the (resized, cropped) image left-right.
        dtype: floating dtype of ``A``.
        corner_origin: ``True`` reproduces mmdet3d's ``apply_img_aug`` / ``point_sample`` (and the MSSF
            authors' ``proj_to_img``), which treat pixel coordinates as corner-origin: resize
            ``u -> s_x u`` and flip ``u -> W - u``. Against the pixels the image operations move, that
            is ``0.5 (s_x - 1)`` px off after a resize and 1 px off after a flip
            (``docs/differences.md``).

    Returns:
        ``(A, (H_out, W_out))``: ``A (3, 3)`` maps homogeneous ``(u, v, 1)`` of the input image to the output.

    Example:
        >>> a, size = image_augmentation_matrix((4, 6), flip=True)
        >>> (a @ torch.tensor([0.0, 1.0, 1.0], dtype=torch.float64)).tolist(), size
        ([5.0, 1.0, 1.0], (4, 6))
    """
    h, w = check_size(image_size, "image_size")
    if not isinstance(corner_origin, bool):
        raise MSSFError(f"corner_origin: expected a bool, got {corner_origin!r}")
    a = torch.eye(3, dtype=dtype)
    if resize is not None:
        nh, nw = check_size(resize, "resize")
        sx, sy = nw / w, nh / h
        ox, oy = (0.0, 0.0) if corner_origin else (0.5 * (sx - 1.0), 0.5 * (sy - 1.0))
        s = torch.tensor([[sx, 0.0, ox], [0.0, sy, oy], [0.0, 0.0, 1.0]], dtype=dtype)
        a, (h, w) = s @ a, (nh, nw)
    if crop is not None:
        if not (isinstance(crop, (tuple, list)) and len(crop) == 4 and all(isinstance(c, int) for c in crop)):
            raise MSSFError(f"crop: expected (top, left, height, width) ints, got {crop!r}")
        top, left, ch, cw = crop
        check_size((ch, cw), "crop height/width")
        c = torch.tensor([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]], dtype=dtype)
        a, (h, w) = c @ a, (ch, cw)
    if flip:
        f = torch.tensor([[-1.0, 0.0, w - (0.0 if corner_origin else 1.0)], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=dtype)
        a = f @ a
    return a, (h, w)


def apply_image_augmentation(lidar2img: Tensor, matrix: Tensor) -> Tensor:
    """``lidar2img' = A @ lidar2img``: the projection into the augmented image (computed in float64).

    Args:
        lidar2img: ``(B, V, 3, 4)`` or ``(B, 3, 4)``, or the same with 4 x 4 matrices (as the projector
            takes them; the last row is kept).
        matrix: ``(3, 3)`` (every sample and camera), ``(B, 3, 3)`` (per sample) or ``(B, V, 3, 3)``
            pixel affine from :func:`image_augmentation_matrix`; its last row must be ``(0, 0, 1)``.

    Returns:
        ``lidar2img'`` of the shape and dtype of ``lidar2img``.
    """
    if not isinstance(lidar2img, Tensor) or lidar2img.dim() not in (3, 4) or tuple(lidar2img.shape[-2:]) not in (
            (3, 4), (4, 4)):
        got = tuple(lidar2img.shape) if isinstance(lidar2img, Tensor) else type(lidar2img).__name__
        raise MSSFError(f"lidar2img: expected shape (B, V, 3, 4) or (B, 3, 4) (or 4 x 4, as the projector "
                        f"takes), got {got}")
    check_floating(lidar2img, "lidar2img")
    if not isinstance(matrix, Tensor) or matrix.dim() < 2 or tuple(matrix.shape[-2:]) != (3, 3):
        got = tuple(matrix.shape) if isinstance(matrix, Tensor) else type(matrix).__name__
        raise MSSFError(f"matrix: expected shape (3, 3), (B, 3, 3) or (B, V, 3, 3), got {got}")
    check_floating(matrix, "matrix")
    b = lidar2img.shape[0]
    allowed = {(3, 3), (b, 3, 3)} | ({(b, lidar2img.shape[1], 3, 3)} if lidar2img.dim() == 4 else set())
    if tuple(matrix.shape) not in allowed:
        raise MSSFError(f"matrix: expected one of {sorted(allowed, key=len)} for lidar2img "
                        f"{tuple(lidar2img.shape)}, got {tuple(matrix.shape)}")
    m = matrix.to(torch.float64)
    last = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=m.device)
    if not torch.equal(m[..., 2, :], last.expand_as(m[..., 2, :])):
        raise MSSFError(f"matrix: expected a pixel affine with last row (0, 0, 1), got {m[..., 2, :].tolist()}")
    if lidar2img.dim() == 4 and m.dim() == 3:
        m = m[:, None]
    out = m.to(lidar2img.device) @ lidar2img[..., :3, :].to(torch.float64)
    if lidar2img.shape[-2] == 4:  # a 4 x 4 matrix (the projector reads its first three rows): keep the last
        out = torch.cat([out, lidar2img[..., 3:, :].to(torch.float64)], dim=-2)
    return out.to(lidar2img.dtype)


