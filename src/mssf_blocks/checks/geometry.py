"""Geometry sanity checks where the camera inputs enter (``FusionInputs``, the projector).

Two kinds (``docs/conventions.md``, "Common mistakes"):

* **shape consistency** (errors, read no data, always on): every image level's size is ``image_size``
  over some stride within one level pixel, levels are finest first, and a channels-last (NHWC) level
  is named as such.
* **coverage** (warnings, read data): the fraction of a sample's voxels that project inside the image,
  where the in-image ones fall (all in the top-left quarter, or all on one spot; on a coarse grid with
  few voxels, the raw points' projections and the principal point tell the quarter), the fraction of voxels
  that hold any of the sample's points, an empty point list. They are warnings, not errors, because a
  real frame can have no voxel in view (an empty road, a camera facing elsewhere); the message lists
  the usual causes. They read tensor values, so they run only where that costs no host
  synchronisation: tensors on the CPU, never while a graph is captured; on an accelerator only when
  :func:`set_geometry_checks` turned them on.
"""

from __future__ import annotations

import math
import warnings
from typing import Optional, Sequence

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import is_tracing
from mssf_blocks.checks.coverage import RunningCoverage
from mssf_blocks.errors import MSSFError, MSSFGeometryWarning

__all__ = ["set_geometry_checks", "geometry_checks_enabled"]

_FORCED: Optional[bool] = None
#: fewer in-image voxels than this: no corner / spot verdict (too few to tell)
_MIN_VOXELS = 8
#: fewer in-image projections than this: no top-left-quarter verdict (a small toy scene may sit there)
_MIN_CORNER = 32
#: top-left-quarter verdict from raw points too: at least this share of the in-image projections in the
#: quarter, and every principal point within (_CENTRE_MIN, _CENTRE_MAX] of image_size (correct frames:
#: share <= 0.11, principal point ~0.5; image_size twice: share >= 0.84, principal point ~0.25; a toy
#: camera whose optical axis meets the image corner, principal point 0, is no verdict; docs/conventions.md)
_QUARTER_SHARE = 0.75
_CENTRE_MIN, _CENTRE_MAX = 0.125, 0.375

_CAUSES = (
    "usual causes: image_size not the size lidar2img projects into (scale, or (W, H) swapped); lidar2img "
    "not a projection (a 4x4 lidar-to-camera transform or the intrinsics alone: it must be K @ [R | t]); "
    "points_to_sensor in the wrong direction (it maps augmented points back to the sensor: the inverse of "
    "augmentation_matrix); voxel_size given as (z, y, x) instead of (x, y, z); a wrong point_range_min or "
    "voxels' stride"
)


def set_geometry_checks(enabled: Optional[bool]) -> None:
    """``True``: run the coverage checks on every device (one host synchronisation per projection on an
    accelerator); ``False``: never; ``None`` (default): on CPU tensors only."""
    global _FORCED
    if enabled is not None and not isinstance(enabled, bool):
        raise MSSFError(f"enabled: expected True, False or None, got {enabled!r}")
    _FORCED = enabled


def geometry_checks_enabled(x: Tensor) -> bool:
    """Whether the data-reading checks run for tensors on ``x``'s device."""
    if _FORCED is False or is_tracing():
        return False
    return bool(_FORCED) or x.device.type == "cpu"


def _fits(h: int, w: int, image_h: int, image_w: int) -> bool:
    """Some stride ``s`` with ``|H / s - h| <= 1`` and ``|W / s - w| <= 1``."""
    return max((h - 1) / image_h, (w - 1) / image_w) <= min((h + 1) / image_h, (w + 1) / image_w)


def check_level_sizes(levels: Sequence[Tensor], image_size: Sequence[int], name: str = "image_features") -> None:
    """Every level ``(B, V, C, H_l, W_l)`` is ``image_size`` over a stride (one level pixel of rounding),
    and the levels are finest first; a channels-last level is named (shapes only, no data read)."""
    if is_tracing():
        return
    try:
        ih, iw = (int(v) for v in image_size)
    except (TypeError, ValueError):
        return  # check_image_size names it
    if ih <= 0 or iw <= 0:
        return
    for l, level in enumerate(levels):
        c, h, w = (int(v) for v in level.shape[-3:])
        if _fits(h, w, ih, iw):
            continue
        if _fits(c, h, ih, iw) and w <= 4096:
            raise MSSFError(
                f"{name}[{l}]: shape {tuple(level.shape)} looks channels-last (NHWC: H={c}, W={h}, C={w} for "
                f"image_size={(ih, iw)}); expected (B, C, H, W): pass level.permute(0, 3, 1, 2)"
                + (" (or permute(0, 1, 4, 2, 3) for (B, V, H, W, C))" if level.dim() == 5 else "")
            )
        if l == 0:
            return  # check_image_size explains level 0 (aspect, swapped (W, H))
        raise MSSFError(
            f"{name}[{l}]: expected (H_l, W_l) = image_size {(ih, iw)} over a stride within one pixel, got "
            f"({h}, {w}); every level must come from the image of image_size"
        )
    sizes = [tuple(int(v) for v in level.shape[-2:]) for level in levels]
    for l in range(1, len(sizes)):
        if sizes[l][0] > sizes[l - 1][0] or sizes[l][1] > sizes[l - 1][1]:
            raise MSSFError(
                f"{name}: expected levels finest first (each level's (H, W) at most the previous one's), got "
                f"sizes {sizes}; reversed (coarsest first)? pass them in order of increasing stride"
            )


def _matrix_hint(lidar2img: Tensor) -> str:
    """What is wrong with a ``(B, V, 3, 4)`` matrix that makes no projection, if recognisable."""
    m = lidar2img.detach().double()[..., :3, :3]
    eye = torch.eye(3, dtype=m.dtype)
    if bool((m @ m.transpose(-1, -2) - eye).abs().amax() < 1e-3):
        return ("; lidar2img's 3x3 block is a rotation: a rigid lidar-to-camera transform, not a projection "
                "(multiply by the camera intrinsics: K @ [R | t])")
    t = lidar2img.detach().double()[..., :3, 3]
    lower = m[..., 1, 0].abs() + m[..., 2, 0].abs() + m[..., 2, 1].abs()
    if bool(((lower + t.abs().sum(-1)) < 1e-9).all()):
        return ("; lidar2img looks like the intrinsics alone ([K | 0]: no rotation from the sensor's axes to "
                "the camera's, no translation): multiply by the sensor-to-camera transform")
    return ""


def check_projection_coverage(uv: Tensor, depth: Tensor, batch_index: Tensor, batch_size: int,
                              image_size: Sequence[int], lidar2img: Tensor, eps: float,
                              monitor: Optional[RunningCoverage] = None, stride: Sequence[int] = (1, 1, 1),
                              raw_uv: Optional[Tensor] = None) -> None:
    """Warn per sample when no voxel lands in the image, or all of them in the top-left quarter or on
    one spot, or (with ``monitor``) when the in-image fraction collapses against its running value (see
    the module doc); ``uv (N, V, 2)`` normalised, ``depth (N, V)``; ``raw_uv (K, 2)``: the in-image
    projections of the raw points, counted with the voxels' for the top-left-quarter verdict (a coarse
    grid has few voxels, the raw points are many)."""
    if uv.shape[0] == 0 or not geometry_checks_enabled(uv):
        return
    h, w = (int(v) for v in image_size)
    inside = (depth > eps) & (uv >= 0).all(-1) & (uv <= 1).all(-1)  # (N, V)
    seen = inside.any(1)
    n_all = torch.bincount(batch_index, minlength=batch_size)
    n_in = torch.bincount(batch_index[seen], minlength=batch_size)
    for b in (n_all > 0).logical_and(n_in == 0).nonzero().flatten().tolist():
        l2i = lidar2img if lidar2img.dim() == 4 else lidar2img[:, None]
        warnings.warn(MSSFGeometryWarning(
            f"projection: none of sample {b}'s {int(n_all[b])} voxels projects inside the image "
            f"(image_size={(h, w)}): the camera contributes nothing; {_CAUSES}{_matrix_hint(l2i[b:b + 1])}"
        ), stacklevel=2)
    if monitor is not None:
        hits, totals = n_in.tolist(), n_all.tolist()
        monitor.observe("projection", stride, hits, totals, [t > 0 and k == 0 for k, t in zip(hits, totals)])
    front = (depth > eps) & torch.isfinite(uv).all(-1)
    pix = uv * uv.new_tensor([w, h])  # pixel positions, half a pixel off at most
    swapped = front & (pix >= 0).all(-1) & (pix[..., 0] <= h) & (pix[..., 1] <= w)
    n_seen, n_swapped = int(inside.sum()), int(swapped.sum())
    if h != w and n_swapped - n_seen >= _MIN_VOXELS and n_swapped > 1.2 * n_seen and not bool(
            (_relative_centre(lidar2img, h, w) >= 0.75).all()):  # (that is image_size too small: _first_call)
        warnings.warn(MSSFGeometryWarning(
            f"projection: {n_seen} voxel projections inside image_size={(h, w)} but {n_swapped} inside "
            f"{(w, h)}: image_size (W, H) swapped? it is (H, W)"
        ), stacklevel=2)
    pts = uv[inside]  # (K, 2) of every in-image (voxel, camera)
    if int(seen.sum()) >= _MIN_VOXELS:
        hi, lo = pts.amax(0), pts.amin(0)
        if bool(((hi - lo) * uv.new_tensor([w, h]) < 2).all()):
            warnings.warn(MSSFGeometryWarning(
                f"projection: all {pts.shape[0]} in-image voxel projections fall within 2 pixels of one spot "
                f"({float(lo[0]) * w:.1f}, {float(lo[1]) * h:.1f}): lidar2img is not a projection?"
                + _matrix_hint(lidar2img if lidar2img.dim() == 4 else lidar2img[:, None])
            ), stacklevel=2)
            return
    if pts.shape[0] >= _MIN_CORNER and bool((pts.amax(0) <= 0.5).all()):
        warnings.warn(MSSFGeometryWarning(
            f"projection: all {pts.shape[0]} in-image voxel projections fall in the top-left quarter of "
            f"image_size={(h, w)} (u <= {float(pts[:, 0].amax()):.3f}, v <= {float(pts[:, 1].amax()):.3f}): is "
            "image_size larger than the image lidar2img projects into (e.g. twice its size)?"
        ), stacklevel=2)
        return
    # A coarse grid has few voxels: the raw points' projections and the principal point (where the optical
    # axis lands) tell the same on the first call (docs/conventions.md gives the measured figures).
    both = pts if raw_uv is None else torch.cat([pts, raw_uv.to(pts.dtype)])
    if both.shape[0] < _MIN_VOXELS:
        return
    share = float((both <= 0.5).all(-1).double().mean())
    centre = _relative_centre(lidar2img, h, w)
    if share >= _QUARTER_SHARE and bool(((centre > _CENTRE_MIN) & (centre <= _CENTRE_MAX)).all()):
        warnings.warn(MSSFGeometryWarning(
            f"projection: {share:.2f} of {both.shape[0]} in-image projections (voxels and raw points) fall in the "
            f"top-left quarter of image_size={(h, w)}, and the principal point lands at "
            f"{tuple(round(float(v), 2) for v in centre.reshape(-1, 2)[0])} of it: is image_size larger than "
            "the image lidar2img projects into (e.g. twice its size)?"
        ), stacklevel=2)


def _relative_centre(lidar2img: Tensor, h: int, w: int) -> Tensor:
    """``(B, V, 2)`` principal points as fractions ``(c_x / W, c_y / H)`` of ``image_size``."""
    return _principal_points(lidar2img) / torch.tensor([w, h], dtype=torch.float64, device=lidar2img.device)


def _principal_points(lidar2img: Tensor) -> Tensor:
    """``(B, V, 2)`` pixel where each camera's optical axis lands: ``M m3 / (m3 . m3)`` for
    ``lidar2img = [M | p]`` with ``m3`` M's last row (``(c_x, c_y)`` of ``K`` for ``K @ [R | t]``, any scale).
    NaN where ``m3`` is zero (no optical axis): every verdict that reads it then gives none."""
    m = (lidar2img if lidar2img.dim() == 4 else lidar2img[:, None]).detach().double()[..., :3, :3]
    p = (m @ m[..., 2, :, None])[..., 0]
    return p[..., :2] / p[..., 2:]


def check_centroid_coverage(has_points: Tensor, batch_index: Tensor, points_batch: Tensor,
                            batch_size: int, monitor: Optional[RunningCoverage] = None,
                            stride: Sequence[int] = (1, 1, 1)) -> None:
    """Warn when a sample has voxels and points but no voxel holds any of them (the voxel grid and
    the points disagree), when there are voxels and no points at all (centres are used), or (with
    ``monitor``) when a sample's fraction of voxels holding a point collapses against its running value."""
    if has_points.shape[0] == 0 or not geometry_checks_enabled(has_points):
        return
    if points_batch.shape[0] == 0:
        warnings.warn(MSSFGeometryWarning(
            f"points: empty, while there are {has_points.shape[0]} voxels: every voxel uses its centre "
            "instead of a centroid; pass the raw points the voxels were built from"
        ), stacklevel=2)
        return
    n_vox = torch.bincount(batch_index, minlength=batch_size)
    n_pts = torch.bincount(points_batch.long().clamp(0, batch_size - 1), minlength=batch_size)
    n_hold = torch.bincount(batch_index[has_points], minlength=batch_size)
    for b in ((n_vox > 0) & (n_pts > 0) & (n_hold == 0)).nonzero().flatten().tolist():
        warnings.warn(MSSFGeometryWarning(
            f"centroids: none of sample {b}'s {int(n_vox[b])} voxels holds any of its {int(n_pts[b])} points: "
            "the voxel grid and the points disagree; check voxel_size (x, y, z order), the voxels' "
            "stride (SparseVoxels.stride), point_range_min and points_batch"
        ), stacklevel=2)
    if monitor is not None:
        hits, totals, pts = n_hold.tolist(), n_vox.tolist(), n_pts.tolist()
        monitor.observe("centroids", stride, hits, totals, [k == 0 and p > 0 for k, p in zip(hits, pts)])


def check_grid(spatial_shape: Sequence[int], voxel_size: Sequence[float], point_range_min: Sequence[float],
               stride: Sequence[int], point_range_max: Optional[Sequence[float]], name: str = "x") -> None:
    """The sparse tensor's ``spatial_shape (D, H, W)`` against the metric grid: with ``point_range_max``
    known, each axis must hold ``(max - min) / (voxel_size * stride)`` cells within one (the rounding
    of strided convolutions). Numbers only, no data read; the message names a permuted axis order."""
    if point_range_max is None:
        return
    extent = [(hi - lo) / (v * s) for hi, lo, v, s in zip(point_range_max[::-1], point_range_min[::-1],
                                                             voxel_size[::-1], stride)]  # (z, y, x)
    shape = tuple(int(v) for v in spatial_shape)

    def fits(cand) -> bool:
        return all(abs(c - e) <= 1.0 for c, e in zip(cand, extent))

    if fits(shape):
        return
    import itertools

    perm = next((p for p in itertools.permutations(shape) if p != shape and fits(p)), None)
    hint = (f"; {perm} would fit: spatial_shape is (D, H, W) = (z, y, x) cells, given in another order?"
            if perm is not None else "; check voxel_size (x, y, z order), the tensor's stride and "
            "the point range")
    raise MSSFError(
        f"{name}.spatial_shape: expected (D, H, W) = ({', '.join(f'{e:.1f}' for e in extent)}) cells within one "
        f"(point range ({tuple(point_range_min)}, {tuple(point_range_max)}) over voxel_size {tuple(voxel_size)} "
        f"x stride {tuple(stride)}), got {shape}{hint}"
    )


def check_indices_in_shape(indices: Tensor, spatial_shape: Sequence[int], name: str = "x") -> None:
    """An spconv tensor's ``(batch, z, y, x)`` indices inside its ``spatial_shape`` (spconv drops the
    rest without a word); data-reading, so gated like the coverage checks."""
    if indices.shape[0] == 0 or not geometry_checks_enabled(indices):
        return
    shape = tuple(int(v) for v in spatial_shape)
    top = [int(v) for v in indices[:, 1:].amax(0).tolist()]
    low = int(indices[:, 1:].amin())
    if low >= 0 and all(t < s for t, s in zip(top, shape)):
        return
    import itertools

    need = tuple(t + 1 for t in top)
    perm = next((p for p in [shape[::-1], *itertools.permutations(shape)]
                 if p != shape and all(n <= s for n, s in zip(need, p))), None) if low >= 0 else None
    raise MSSFError(
        f"{name}.indices: expected (batch, z, y, x) inside spatial_shape {shape} (D, H, W), got z, y, x up to "
        f"{tuple(top)} (min {low}); spconv would drop those voxels"
        + (f"; they fit {perm}: spatial_shape given in (W, H, D) or another order?" if perm is not None else "")
    )


#: fewer rows than this: no verdict on a batch-index column (a toy cloud of a few points may sit at x = 0)
_MIN_BATCH_COLUMN_ROWS = 8


def check_batch_column(points: Tensor, points_batch: Tensor, name: str = "points",
                       batch_name: str = "points_batch") -> None:
    """Error when ``points[:, 0]`` equals ``points_batch`` on every row: OpenPCDet's ``(b, x, y, z, ...)``
    rows passed where ``(x, y, z, ...)`` rows are expected (the batch index read as x, x as y, y as z).

    Only for ``(P, >=4)`` points of at least 8 rows (a measured x never equals the integer sample index of
    every point of a cloud); reads data, so gated like the warnings (:func:`geometry_checks_enabled`).
    """
    if (points.dim() != 2 or points.shape[1] < 4 or points.shape[0] < _MIN_BATCH_COLUMN_ROWS
            or not isinstance(points_batch, Tensor) or points_batch.shape != points.shape[:1]
            or not geometry_checks_enabled(points)):
        return
    if bool((points[:, 0] == points_batch.to(points.dtype)).all()):
        raise MSSFError(
            f"{name}: expected rows (x, y, z, ...), got shape {tuple(points.shape)} whose column 0 equals "
            f"{batch_name} on all {points.shape[0]} rows: OpenPCDet's (b, x, y, z, ...) layout? pass "
            f"{name}[:, 1:] (and {batch_name}={name}[:, 0].long())"
        )


#: |yaw| above this (radians) in a box: degrees. Boxes from [-pi, pi] through a flip (pi - yaw: up to 2 pi)
#: and a random rotation (the recipes' +-pi/4) stay below 2.25 pi; degrees exceed it from 9.5 degrees on
_MAX_YAW = 3 * math.pi


def check_yaw_radians(boxes: Tensor, name: str) -> None:
    """Warning when a box's yaw (column 6) exceeds 3 pi in magnitude: yaw in degrees (a real box's yaw can
    be unwrapped, so a warning, not an error). Reads data: gated (:func:`geometry_checks_enabled`)."""
    if boxes.shape[0] == 0 or not geometry_checks_enabled(boxes):
        return
    top = float(boxes[:, 6].abs().max())
    if top > _MAX_YAW:
        warnings.warn(
            f"{name}: yaw (column 6) up to {top:.4g} in magnitude, above 3 pi: degrees? pass radians "
            "(torch.deg2rad); yaw is about +z, counter-clockwise from +x", MSSFGeometryWarning, stacklevel=3)


#: fewer logits than this: no verdict on probabilities passed as logits
_MIN_LOGITS = 32


def check_logits_not_probabilities(logits: Tensor, name: str = "logits") -> None:
    """Warning when every one of at least 32 logits lies in ``[0, 1]``: sigmoid scores (the head's
    ``scores``) passed where logits are expected, which trains towards the wrong targets (a score of 0.1
    reads as probability 0.52). A head's logits take both signs (PyTorch's init centres them on 0; a
    trained head gives background voxels negative ones). Reads data: gated."""
    if logits.numel() < _MIN_LOGITS or not geometry_checks_enabled(logits):
        return
    lo, hi = torch.aminmax(logits.detach())
    if float(lo) >= 0.0 and float(hi) <= 1.0:
        warnings.warn(
            f"{name}: all {logits.numel()} values lie in [{float(lo):.3g}, {float(hi):.3g}], within [0, 1]: "
            "sigmoid scores passed as logits? pass the logits (head(x, return_logits=True)[2]); the loss "
            "applies the sigmoid itself", MSSFGeometryWarning, stacklevel=3)


#: boxes in another frame than the voxels: every box at least this far (metres) above or below every voxel
#: centroid of its sample, in samples of at least _MIN_FRAME_VOXELS voxels
_FRAME_GAP = 1.0
_MIN_FRAME_VOXELS = 16


def check_boxes_frame(centroids: Tensor, batch_index: Tensor, gt_boxes: Sequence[Tensor], origin: str) -> None:
    """Warning when, in every sample with boxes and at least 16 voxels, every box lies entirely above (or below)
    all of its sample's voxel centroids by more than 1 m: boxes in the camera frame (KITTI's label files: ``z``
    the depth, 5-50 m; ``y`` down) given where the sensor frame (``z`` up) is expected, so no voxel is ever
    foreground. Boxes stand on the ground the points see, so a real frame overlaps them in height. Reads data:
    gated (:func:`geometry_checks_enabled`), one read-back for the batch."""
    if centroids.shape[0] == 0 or not geometry_checks_enabled(centroids):
        return
    b = batch_index.long()
    n = len(gt_boxes)
    z = centroids[:, 2].detach().double()
    zmax = torch.full((n,), -math.inf, dtype=torch.float64).scatter_reduce(0, b, z, "amax")
    zmin = torch.full((n,), math.inf, dtype=torch.float64).scatter_reduce(0, b, z, "amin")
    count = torch.bincount(b, minlength=n)
    verdicts = []
    for i, boxes in enumerate(gt_boxes):
        if boxes.shape[0] == 0 or int(count[i]) < _MIN_FRAME_VOXELS:
            continue
        bx = boxes[:, :6].detach().double().cpu()
        bottom = bx[:, 2] - (0.0 if origin == "bottom" else bx[:, 5] / 2)
        top = bottom + bx[:, 5]
        above = float(bottom.min()) - float(zmax[i])
        below = float(zmin[i]) - float(top.max())
        verdicts.append((i, max(above, below), float(bottom.min()), float(zmin[i]), float(zmax[i])))
    if verdicts and all(v[1] > _FRAME_GAP for v in verdicts):
        i, gap, bottom, lo, hi = verdicts[0]
        warnings.warn(
            f"gt_boxes[{i}]: every box lies {gap:.3g} m or more above or below all of the sample's voxel "
            f"centroids (box bottoms from {bottom:.3g} m, centroid z in [{lo:.3g}, {hi:.3g}] m), in every sample "
            "with boxes: boxes in the camera frame (x right, y down, z forward: KITTI label files)? pass them in "
            "the sensor frame of the points (x, y, z, dx, dy, dz, yaw with z up)", MSSFGeometryWarning, stacklevel=3)
