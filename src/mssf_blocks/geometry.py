"""``VoxelCentroidProjector``: voxel centroids of a sparse tensor, projected into the cameras.

This is the first half of every MSSF fusion block (paper Sec. III-C, eq. 1-2): find the centroid of
the raw points inside each non-empty voxel (its centre if it holds none), then project it with the
camera matrices to normalised image coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from ._checks import check_floating, check_points, check_radians, check_shape, check_triple
from ._running_coverage import RunningCoverage
from ._first_call import check_image_size_small, check_points_in_voxels, check_points_to_sensor, project_raw
from ._sanity import check_centroid_coverage, check_projection_coverage, geometry_checks_enabled, set_geometry_checks
from .errors import MSSFError
from .functional.geometry import project_points, voxel_centroids
from .sparse import SparseVoxels

__all__ = [
    "VoxelCentroidProjector", "CentroidProjection", "augmentation_matrix", "image_augmentation_matrix",
    "apply_image_augmentation", "set_geometry_checks",
]


@dataclass(frozen=True)
class CentroidProjection:
    """What a fusion block needs to sample the image for every voxel.

    Attributes:
        uv: ``(N, V, 2)`` normalised sampling coordinates ``((u + 0.5) / W, (v + 0.5) / H)``.
        depth: ``(N, V)`` camera depth.
        valid: ``(N, V)`` depth above ``eps`` and inside the image.
        centroid: ``(N, 3)`` metric ``(x, y, z)`` centroid (centre where the voxel holds no point).
        has_points: ``(N,)`` which voxels hold raw points.
        batch_index: ``(N,)`` int64 batch index of every voxel.
    """

    uv: Tensor
    depth: Tensor
    valid: Tensor
    centroid: Tensor
    has_points: Tensor
    batch_index: Tensor

    @property
    def num_cameras(self) -> int:
        return int(self.uv.shape[1])


class VoxelCentroidProjector(nn.Module):
    """Centroids of a :class:`SparseVoxels` projected into ``V`` cameras.

    Args:
        eps: depths ``<= eps`` are invalid (behind the camera).
        point_range_max: optional ``(x, y, z)`` upper corner of the point-cloud range; points at or
            above it are ignored (by default, points beyond the grid are ignored).
        half_pixel: ``True`` (default): ``uv = ((u + 0.5) / W, (v + 0.5) / H)``, pixel ``i``'s centre at
            ``(i + 0.5) / W`` (every FPN level samples the same spot). ``False``: ``uv = (u / W, v / H)``,
            the paper's ``c = (u / W, v / H)`` taken literally and the MSSF authors' reference points
            (half a base pixel to the left and up; :mod:`mssf_blocks.compat.mssf_official`).
        inside_image_only: ``True`` (default): ``valid`` needs the point inside the image; a voxel
            outside gets an exact zero image feature. ``False``: ``valid`` is ``depth > eps`` only, so
            an out-of-image voxel in front of the camera is sampled (zero padding; MSDFF offsets may
            reach into the image) and goes through the samplers' output layers, as in the authors'
            code.

    Shapes:
        - voxels: N voxels at any stride; points ``(P, 3)`` x, y, z (slice other columns off: extra
          columns are refused); points_batch ``(P,)``.
        - lidar2img ``(B, V, 3, 4)`` or ``(B, 3, 4)``; points_to_sensor ``(B, 4, 4)``.
        - output: :class:`CentroidProjection` with ``uv (N, V, 2)``, ``depth (N, V)``, ``valid (N, V)``,
          ``centroid (N, 3)``, ``has_points (N,)``, in the dtype of ``points`` (float32 for float16 /
          bfloat16 points: half-precision centroids would be off by decimetres).

    Example:
        >>> import torch
        >>> from mssf_blocks import SparseVoxels, VoxelCentroidProjector
        >>> vox = SparseVoxels(torch.zeros(1, 2), torch.tensor([[0, 0, 0, 0]], dtype=torch.int32),
        ...                    (1, 1, 1), 1, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
        >>> pts = torch.tensor([[0.25, 0.5, 0.75]])
        >>> l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]])  # depth 1, u = x, v = y
        >>> out = VoxelCentroidProjector()(vox, pts, torch.zeros(1, dtype=torch.long), l2i, (4, 4))
        >>> out.centroid, out.uv
        (tensor([[0.2500, 0.5000, 0.7500]]), tensor([[[0.1875, 0.2500]]]))
    """

    def __init__(self, eps: float = 1e-5, point_range_max: Optional[Sequence[float]] = None,
                 half_pixel: bool = True, inside_image_only: bool = True) -> None:
        super().__init__()
        for name, flag in (("half_pixel", half_pixel), ("inside_image_only", inside_image_only)):
            if not isinstance(flag, bool):
                raise MSSFError(f"{name}: expected a bool, got {flag!r}")
        self.half_pixel, self.inside_image_only = half_pixel, inside_image_only
        if not (isinstance(eps, (int, float)) and eps >= 0):
            raise MSSFError(f"eps: expected a non-negative float, got {eps!r}")
        self.eps = float(eps)
        self.point_range_max = (
            None if point_range_max is None else check_triple(point_range_max, "point_range_max", float)
        )
        #: running per-sample coverage (in-image and centroid fractions) per voxel stride, for the
        #: collapse warnings (docs/conventions.md, "Common mistakes"); plain numbers, not in the state_dict
        self.coverage = RunningCoverage()

    def forward(
        self,
        voxels: SparseVoxels,
        points: Tensor,
        points_batch: Tensor,
        lidar2img: Tensor,
        image_size: Sequence[int],
        points_to_sensor: Optional[Tensor] = None,
    ) -> CentroidProjection:
        if not isinstance(voxels, SparseVoxels):
            raise MSSFError(f"voxels: expected SparseVoxels, got {type(voxels).__name__}")
        l2i_batch = lidar2img.shape[0] if isinstance(lidar2img, Tensor) and lidar2img.dim() >= 3 else None
        if l2i_batch is not None and l2i_batch != voxels.batch_size:
            raise MSSFError(
                f"lidar2img: expected batch size {voxels.batch_size} (voxels.batch_size), "
                f"got shape {tuple(lidar2img.shape)}"
            )
        if points_to_sensor is not None:
            check_shape(points_to_sensor, "points_to_sensor", (voxels.batch_size, 4, 4))
        check_points(points, points_batch, exact_xyz=True)
        if points.dtype in (torch.float16, torch.bfloat16):
            # Centroids (sums of coordinates) and projections in half precision would be off by
            # decimetres and pixels: compute them in float32 (the coordinates themselves are exact).
            points = points.float()
        centroid, has_points = voxel_centroids(
            points, points_batch, voxels.coords, voxels.spatial_shape, voxels.batch_size,
            voxels.voxel_size, voxels.point_range_min, voxels.stride, self.point_range_max,
        )
        batch_index = voxels.batch_index
        proj = project_points(centroid, batch_index, lidar2img, image_size, points_to_sensor, self.eps)
        uv, valid = proj.uv, proj.valid
        # (warnings; they read data only where that costs no host synchronisation: _sanity's doc)
        checks = geometry_checks_enabled(uv) and uv.shape[0] > 0 and points.shape[0] > 0
        raw_uv, raw_inside = (project_raw(points, points_batch, lidar2img, image_size, points_to_sensor, self.eps)
                              if checks else (None, None))
        check_projection_coverage(uv, proj.depth, batch_index, voxels.batch_size, image_size, lidar2img, self.eps,
                                  getattr(self, "coverage", None), voxels.stride,
                                  raw_uv=None if raw_uv is None else raw_uv[raw_inside])
        check_centroid_coverage(has_points, batch_index, points_batch, voxels.batch_size,
                                getattr(self, "coverage", None), voxels.stride)
        if checks:  # first-call consistency of voxels, points and points_to_sensor (_first_call's doc)
            check_points_in_voxels(points, points_batch, voxels.coords, batch_index, voxels.spatial_shape,
                                   voxels.batch_size, voxels.voxel_size, voxels.point_range_min, voxels.stride,
                                   self.point_range_max, has_points)
            check_image_size_small(raw_uv, raw_inside, lidar2img, image_size)
            if points_to_sensor is not None:
                check_points_to_sensor(points, points_batch, lidar2img, image_size, points_to_sensor, raw_inside,
                                       voxels.batch_size, self.eps)
        ok_depth = proj.depth > self.eps
        if not self.half_pixel:  # u / W (project_points validated image_size)
            h, w = (int(x) for x in image_size)
            uv = proj.pixel / torch.tensor([w, h], dtype=proj.pixel.dtype, device=proj.pixel.device)
            uv = torch.where(ok_depth[..., None], uv, torch.full_like(uv, -1.0))
        if not self.inside_image_only:
            valid = ok_depth
        elif not self.half_pixel:  # inside the image in the u / W coordinates
            valid = ok_depth & (uv >= 0).all(dim=-1) & (uv <= 1).all(dim=-1)
        return CentroidProjection(
            uv=uv, depth=proj.depth, valid=valid, centroid=centroid,
            has_points=has_points, batch_index=batch_index,
        )

    def extra_repr(self) -> str:
        extra = "" if self.half_pixel and self.inside_image_only else (
            f", half_pixel={self.half_pixel}, inside_image_only={self.inside_image_only}")
        return f"eps={self.eps}, point_range_max={self.point_range_max}{extra}"


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
    h, w = _check_size(image_size, "image_size")
    if not isinstance(corner_origin, bool):
        raise MSSFError(f"corner_origin: expected a bool, got {corner_origin!r}")
    a = torch.eye(3, dtype=dtype)
    if resize is not None:
        nh, nw = _check_size(resize, "resize")
        sx, sy = nw / w, nh / h
        ox, oy = (0.0, 0.0) if corner_origin else (0.5 * (sx - 1.0), 0.5 * (sy - 1.0))
        s = torch.tensor([[sx, 0.0, ox], [0.0, sy, oy], [0.0, 0.0, 1.0]], dtype=dtype)
        a, (h, w) = s @ a, (nh, nw)
    if crop is not None:
        if not (isinstance(crop, (tuple, list)) and len(crop) == 4 and all(isinstance(c, int) for c in crop)):
            raise MSSFError(f"crop: expected (top, left, height, width) ints, got {crop!r}")
        top, left, ch, cw = crop
        _check_size((ch, cw), "crop height/width")
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


def _check_size(size, name: str) -> Tuple[int, int]:
    if not (isinstance(size, (tuple, list, torch.Size)) and len(size) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        raise MSSFError(f"{name}: expected (H, W) positive ints, got {size!r}")
    return int(size[0]), int(size[1])
