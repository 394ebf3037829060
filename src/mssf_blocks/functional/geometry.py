"""Pure geometry functions: voxel centres, voxel centroids and camera projection.

Conventions (see ``docs/conventions.md``):

* coords are ``(batch, z, y, x)`` int32 at a stride ``(sz, sy, sx)`` of the base grid;
* the metric centre of a voxel is ``(index + 0.5) * voxel_size * stride + point_range_min``;
* ``lidar2img`` maps homogeneous sensor points to ``(u*d, v*d, d)`` with OpenCV pixel coordinates
  (pixel ``i``'s centre at ``i``); normalised sampling coordinates are ``((u + 0.5) / W, (v + 0.5) / H)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import (
    INDEX_DTYPES,
    autocast_off,
    check_dtype,
    check_finite,
    check_floating,
    check_index_range,
    check_points,
    check_shape,
)
from mssf_blocks.checks.arguments import check_image_size, check_triple
from mssf_blocks.checks.tensors import check_centroid_inputs
from mssf_blocks.static_path import use_static_path
from mssf_blocks.errors import MSSFError
from mssf_blocks.static_path import segment_slots
from mssf_blocks.checks.matrices import check_points_to_sensor_matrix

__all__ = [
    "voxel_centers",
    "voxel_centroids",
    "voxel_centroids_reference",
    "project_points",
    "Projection",
    "normalize_lidar2img",
]



def voxel_centers(
    coords: Tensor,
    voxel_size: Sequence[float],
    point_range_min: Sequence[float],
    stride: Sequence[int] = (1, 1, 1),
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Metric centre of voxels.

    Args:
        coords: ``(N, 4)`` integer ``(batch, z, y, x)``.
        voxel_size: base-grid ``(x, y, z)`` voxel size in metres.
        point_range_min: ``(x, y, z)`` lower corner of the grid.
        stride: ``(sz, sy, sx)`` of ``coords`` relative to the base grid.
        dtype: floating dtype of the result.

    Returns:
        ``(N, 3)`` ``(x, y, z)`` centres: ``(index + 0.5) * voxel_size * stride + point_range_min``.
    """
    check_shape(coords, "coords", ("N", 4))
    check_dtype(coords, "coords", INDEX_DTYPES)
    vs = check_triple(voxel_size, "voxel_size", float, positive=True)
    lo = check_triple(point_range_min, "point_range_min", float)
    sz, sy, sx = check_triple(stride, "stride", int, positive=True)
    step = torch.tensor([vs[0] * sx, vs[1] * sy, vs[2] * sz], dtype=dtype, device=coords.device)
    origin = torch.tensor(lo, dtype=dtype, device=coords.device)
    xyz = coords[:, [3, 2, 1]].to(dtype)
    return (xyz + 0.5) * step + origin


def _grid_keys(coords: Tensor, spatial_shape: Tuple[int, int, int]) -> Tensor:
    """Linear int64 key of ``(batch, z, y, x)`` rows (unique per voxel of a batch)."""
    d, h, w = spatial_shape
    c = coords.long()
    return ((c[:, 0] * d + c[:, 1]) * h + c[:, 2]) * w + c[:, 3]


def _point_keys(
    points: Tensor,
    points_batch: Tensor,
    voxel_size: Tuple[float, float, float],
    point_range_min: Tuple[float, float, float],
    point_range_max: Optional[Tuple[float, float, float]],
    stride: Tuple[int, int, int],
    spatial_shape: Tuple[int, int, int],
) -> Tensor:
    """``(P,)`` int64 key (as :func:`_grid_keys`) of the voxel at ``stride`` holding every point; ``-1``
    for points outside the range or the grid. Built column by column to keep temporaries at ``O(P)``."""
    d, h, w = spatial_shape
    sz, sy, sx = stride
    key = points_batch.long()
    inside = torch.ones_like(key, dtype=torch.bool)
    # Axis order of the key: z, y, x (coords order); columns of points: x, y, z.
    for col, size, step, s in ((2, d, voxel_size[2], sz), (1, h, voxel_size[1], sy), (0, w, voxel_size[0], sx)):
        coord = points[:, col]
        base = torch.floor((coord - point_range_min[col]) / step).long()
        if point_range_max is not None:
            inside &= coord < point_range_max[col]
        idx = base if s == 1 else torch.div(base, s, rounding_mode="floor")
        inside &= (base >= 0) & (idx < size)
        key = key * size + idx
    return torch.where(inside, key, torch.full_like(key, -1))


def voxel_centroids(
    points: Tensor,
    points_batch: Tensor,
    coords: Tensor,
    spatial_shape: Sequence[int],
    batch_size: int,
    voxel_size: Sequence[float],
    point_range_min: Sequence[float],
    stride: Sequence[int] = (1, 1, 1),
    point_range_max: Optional[Sequence[float]] = None,
) -> Tuple[Tensor, Tensor]:
    """Mean of the raw points inside every non-empty voxel (its centre where it holds none).

    A point belongs to voxel ``(b, z, y, x)`` at stride ``(sz, sy, sx)`` when its base-grid index
    ``floor((p - point_range_min) / voxel_size)`` divided (floor) by the stride equals ``(x, y, z)`` and
    its batch index is ``b``. Points below ``point_range_min``, at or above ``point_range_max`` (when
    given; otherwise beyond the grid) are ignored. The join is one ``torch.unique`` over the voxel keys
    and the point keys together (a sort): memory ``O(P + N)``, never a dense ``B x D x H x W`` table.
    Duplicate coordinate rows all receive the same centroid.

    Args:
        points: ``(P, 3+)`` floating points, ``x, y, z`` first (extra columns are ignored).
        points_batch: ``(P,)`` integer batch index of every point.
        coords: ``(N, 4)`` integer ``(batch, z, y, x)`` voxel indices at ``stride``.
        spatial_shape: ``(D, H, W)`` of the grid at ``stride``.
        batch_size: ``B``.
        voxel_size: base-grid ``(x, y, z)`` voxel size.
        point_range_min: ``(x, y, z)`` lower corner.
        stride: ``(sz, sy, sx)``.
        point_range_max: optional ``(x, y, z)`` upper corner of the point-cloud range.

    Returns:
        ``centroids (N, 3)`` (float64 for float64 ``points``, else float32: half-precision points are
        read as float32) and ``has_points (N,)`` bool (False where the centre was used).
    """
    spatial_shape, batch_size, stride, voxel_size, lo, hi = check_centroid_inputs(
        points, points_batch, coords, spatial_shape, batch_size, stride, voxel_size, point_range_min,
        point_range_max,
    )
    n = coords.shape[0]
    # float32 at least: in half precision the voxel keys (floor of coordinate / voxel size) and the sums
    # would be off by voxels and decimetres at 50 m.
    dtype, device = (torch.float64 if points.dtype == torch.float64 else torch.float32), points.device
    points = points[:, :3].to(dtype)
    centers = voxel_centers(coords, voxel_size, lo, stride, dtype=dtype)
    if n == 0 or points.shape[0] == 0:
        return centers, torch.zeros(n, dtype=torch.bool, device=device)

    # One sort joins points to voxels: unique over voxel keys and point keys together gives every
    # row and every point its slot; points accumulate into slots, and only the voxels' slots are
    # read back (points of no voxel, or outside the range with key -1, land in slots nobody reads).
    voxel_keys = _grid_keys(coords, spatial_shape)
    point_keys = _point_keys(points, points_batch, voxel_size, lo, hi, stride, spatial_shape)
    keys = torch.cat([voxel_keys, point_keys])
    if use_static_path():  # compile / export: a slot per key occurrence (N + P), no data-dependent size
        slot = segment_slots(keys)
        m = keys.shape[0]
    else:
        uniq, slot = torch.unique(keys, sorted=True, return_inverse=True)
        m = uniq.shape[0]  # slot.max() + 1, already known on the host (no second synchronisation)
    row_slot, point_slot = slot[:n], slot[n:]

    sums = torch.zeros(m, 3, dtype=dtype, device=device).index_add_(0, point_slot, points[:, :3])
    counts = torch.zeros(m, dtype=dtype, device=device).index_add_(
        0, point_slot, torch.ones_like(point_slot, dtype=dtype)
    )
    counts_rows = counts[row_slot]
    has_points = counts_rows > 0
    means = sums[row_slot] / counts_rows.clamp(min=1)[:, None]
    centroids = torch.where(has_points[:, None], means, centers)
    return centroids, has_points


def voxel_centroids_reference(
    points: Tensor,
    points_batch: Tensor,
    coords: Tensor,
    spatial_shape: Sequence[int],
    batch_size: int,
    voxel_size: Sequence[float],
    point_range_min: Sequence[float],
    stride: Sequence[int] = (1, 1, 1),
    point_range_max: Optional[Sequence[float]] = None,
) -> Tuple[Tensor, Tensor]:
    """Slow per-voxel loop with the same semantics as :func:`voxel_centroids` (for tests)."""
    spatial_shape, batch_size, stride, voxel_size, lo, hi = check_centroid_inputs(
        points, points_batch, coords, spatial_shape, batch_size, stride, voxel_size, point_range_min,
        point_range_max,
    )
    pts = points[:, :3].tolist()
    pb = points_batch.tolist()
    sz, sy, sx = stride
    d, h, w = spatial_shape
    import math

    members: dict = {}
    for (x, y, z), b in zip(pts, pb):
        if hi is not None and not (x < hi[0] and y < hi[1] and z < hi[2]):
            continue
        ix = math.floor((x - lo[0]) / voxel_size[0])
        iy = math.floor((y - lo[1]) / voxel_size[1])
        iz = math.floor((z - lo[2]) / voxel_size[2])
        if ix < 0 or iy < 0 or iz < 0:
            continue
        key = (b, iz // sz, iy // sy, ix // sx)
        if key[1] >= d or key[2] >= h or key[3] >= w:
            continue
        members.setdefault(key, []).append((x, y, z))
    dtype = torch.float64 if points.dtype == torch.float64 else torch.float32
    centers = voxel_centers(coords, voxel_size, lo, stride, dtype=dtype)
    out = centers.clone()
    has = torch.zeros(coords.shape[0], dtype=torch.bool)
    for i, row in enumerate(coords.tolist()):
        pts_in = members.get(tuple(row))
        if pts_in:
            n = len(pts_in)
            out[i] = torch.tensor([sum(p[k] for p in pts_in) / n for k in range(3)], dtype=dtype)
            has[i] = True
    return out, has.to(points.device)


def normalize_lidar2img(lidar2img: Tensor, batch_size: Optional[int] = None) -> Tensor:
    """Validate ``lidar2img`` and return it as ``(B, V, 3, 4)`` (a ``(B, 3, 4)`` input means V = 1)."""
    if not isinstance(lidar2img, Tensor):
        raise MSSFError(f"lidar2img: expected a torch.Tensor (B, V, 3, 4), got {type(lidar2img).__name__}")
    if lidar2img.dim() == 3:
        lidar2img = lidar2img[:, None]
    dims = {} if batch_size is None else {"B": batch_size}
    if lidar2img.dim() != 4 or tuple(lidar2img.shape[2:]) not in ((3, 4), (4, 4)):
        raise MSSFError(
            f"lidar2img: expected shape (B, V, 3, 4) or (B, 3, 4), got {tuple(lidar2img.shape)}"
        )
    try:
        check_shape(lidar2img, "lidar2img", ("B", "V", None, 4), dims)
    except MSSFError as exc:
        raise MSSFError(f"{exc} (voxels/points have batch_size={batch_size})") from None
    check_floating(lidar2img, "lidar2img")
    check_finite(lidar2img, "lidar2img")
    return lidar2img[:, :, :3, :]


@dataclass(frozen=True)
class Projection:
    """Result of :func:`project_points`.

    Attributes:
        uv: ``(N, V, 2)`` normalised sampling coordinates ``((u + 0.5) / W, (v + 0.5) / H)``; where
            the depth is invalid they are set to ``-1`` (outside the image, so sampling reads zeros).
        depth: ``(N, V)`` depth ``d`` in the camera frame.
        valid: ``(N, V)`` ``depth > eps`` and the point inside the image (``0 <= uv <= 1``).
        pixel: ``(N, V, 2)`` OpenCV pixel coordinates ``(u, v)`` (``-1`` where the depth is invalid).
    """

    uv: Tensor
    depth: Tensor
    valid: Tensor
    pixel: Tensor


def project_points(
    points: Tensor,
    points_batch: Tensor,
    lidar2img: Tensor,
    image_size: Sequence[int],
    points_to_sensor: Optional[Tensor] = None,
    eps: float = 1e-5,
) -> Projection:
    """Project sensor-frame points into every camera.

    Args:
        points: ``(N, 3+)`` floating ``x, y, z`` (further columns ignored), in the (possibly
            augmented) point-cloud frame.
        points_batch: ``(N,)`` integer batch index.
        lidar2img: ``(B, V, 3, 4)`` (or ``(B, 3, 4)``, or ``4 x 4`` homogeneous) mapping homogeneous
            sensor points to ``(u*d, v*d, d)``.
        image_size: ``(H, W)`` of the image the features were computed from.
        points_to_sensor: optional ``(B, 4, 4)`` affine map from augmented points back to the sensor
            frame (the inverse of flip/rotation/scale/translation augmentation).
        eps: depths ``<= eps`` are invalid (behind or on the camera plane).

    Returns:
        :class:`Projection` with ``uv (N, V, 2)``, ``depth (N, V)``, ``valid (N, V)``, ``pixel``,
        float64 for float64 ``points``, else float32; computed in float32 or better (float64 when
        any input is float64), with autocast disabled. Gradients flow to ``points`` (and the
        matrices) through valid-depth entries only; nothing is NaN.
    """
    check_points(points, points_batch, rows="N")
    # (one device: lidar2img built on the CPU from metas beside GPU points; else torch's error from the einsum)
    for t, tname in ((lidar2img, "lidar2img"), (points_to_sensor, "points_to_sensor"), (points_batch, "points_batch")):
        if isinstance(t, torch.Tensor) and t.device != points.device:
            raise MSSFError(f"{tname}: expected device {points.device} (of points), got {t.device}; move it with "
                            f".to(points.device)")
    check_finite(points[:, :3], "points[:, :3]")
    check_dtype(points_batch, "points_batch", INDEX_DTYPES)
    l2i = normalize_lidar2img(lidar2img)
    batch_size = l2i.shape[0]
    check_index_range(points_batch, "points_batch", batch_size, "lidar2img.shape[0] (batch size)")
    h, w = check_image_size(image_size)
    if not eps >= 0:
        raise MSSFError(f"eps: expected a non-negative float, got {eps!r}")

    # The projection runs in float32 or better whatever the autocast state: autocast would round the
    # matrix products to bfloat16 (pixels off by up to ~10 px on a 1936-wide VoD frame). It runs in
    # float64 when any input is float64 (a float64 lidar2img keeps its precision even for float32
    # points: the product of 1,500-pixel focal lengths and 50 m coordinates loses ~1e-4 px in float32);
    # results are float64 for float64 points, else float32.
    out_dtype = torch.float64 if points.dtype == torch.float64 else torch.float32
    wide = any(t is not None and t.dtype == torch.float64 for t in (points, l2i, points_to_sensor))
    dtype = torch.float64 if wide else torch.float32
    with autocast_off(points.device.type):
        b = points_batch.long()
        xyz = points[:, :3].to(dtype)
        ones = torch.ones_like(xyz[:, :1])
        hom = torch.cat([xyz, ones], dim=1)  # (N, 4)
        if points_to_sensor is not None:
            p2s = check_points_to_sensor_matrix(points_to_sensor, batch_size).to(dtype)
            hom = torch.einsum("nij,nj->ni", p2s[b], hom)
        cam = torch.einsum("nvij,nj->nvi", l2i.to(dtype)[b], hom)  # (N, V, 3)
        depth = cam[..., 2]
        ok_depth = depth > eps
        safe_d = torch.where(ok_depth, depth, torch.ones_like(depth))
        pixel = cam[..., :2] / safe_d[..., None]
        pixel = torch.where(ok_depth[..., None], pixel, torch.full_like(pixel, -1.0))
        size = torch.tensor([w, h], dtype=dtype, device=points.device)
        uv = (pixel + 0.5) / size
        uv = torch.where(ok_depth[..., None], uv, torch.full_like(uv, -1.0))
        # (u and v compared one by one, not all(dim=-1): ONNX exports all() as ReduceMin, whose opset
        # 18 -> 17 conversion fails)
        u_img, v_img = uv[..., 0], uv[..., 1]
        valid = ok_depth & (u_img >= 0) & (v_img >= 0) & (u_img <= 1) & (v_img <= 1)
        uv, depth, pixel = uv.to(out_dtype), depth.to(out_dtype), pixel.to(out_dtype)
    return Projection(uv=uv, depth=depth, valid=valid, pixel=pixel)
