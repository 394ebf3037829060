"""First-call consistency checks of the voxels, the raw points and the projection (``docs/conventions.md``,
"Common mistakes").

The coverage checks of :mod:`._sanity` warn when a coverage is *zero*, and :mod:`._running_coverage` when
it collapses against its running value. On a coarse grid (0.2 x 0.2 x 0.25 m) a wrong grid still leaves
some voxels holding points by chance, and a mistake present from the first step has no correct running
value to fall from. The checks here compare the inputs of one call with each other, so they need no
warm-up:

* **points in voxels**: the fraction of a sample's raw points on the grid whose voxel at the voxels'
  stride is one of the sample's voxels. Voxels built from these points (a voxeliser, then submanifold
  convolutions or strided ones of kernel 3, stride 2, padding 1, which keep the voxel ``floor(i / 2)``
  of every input voxel ``i``) hold every such point: the fraction is 1.0 at every stride. A permuted
  ``voxel_size``, a wrong ``stride``, ``point_range_min`` or coords order puts most points
  beside the voxels even where a few still meet one by chance.
* **voxels without points**: a sample with voxels and none of the points (``points_batch`` labels them
  all as other samples), while other samples have points.
* **points_to_sensor counterfactual**: the in-image fraction of a sample's raw points with
  ``points_to_sensor`` against the fraction with its inverse and with none. The correct matrix undoes
  the augmentation, so neither alternative does much better; the forward matrix passed by mistake
  doubles the augmentation, and its inverse restores the view.
* the raw points' in-image projections also feed the top-left-quarter verdict of
  :func:`._sanity.check_projection_coverage` (``image_size`` too large): there are far more raw points
  than coarse voxels; and the other way round, far more of them inside twice ``image_size`` than inside
  it, with the principal point at the image's far corner: ``image_size`` too small.

All of them read tensor values: gated like the coverage checks (:func:`._sanity.geometry_checks_enabled`).
The thresholds and the distributions they were chosen from are in ``docs/conventions.md``
(``benchmarks/first_call_spread.py`` measures them).
"""

from __future__ import annotations

import warnings
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.geometry import _relative_centre
from mssf_blocks.errors import MSSFGeometryWarning
from mssf_blocks.functional.geometry import _grid_keys, _point_keys, project_points

#: warn when fewer than this fraction of a sample's on-grid raw points lie in one of its voxels
POINTS_IN_VOXELS_MIN = 0.5
#: no points-in-voxels verdict on a sample with fewer on-grid points (a handful is noise)
MIN_POINTS = 8
#: points_to_sensor: warn when the inverse (or no matrix) puts at least this many times more of a sample's
#: raw points in the image, and at least MIN_GAIN more of them as a fraction (correct inputs: at most 1.02x)
INVERSE_RATIO = 1.5
MIN_GAIN = 0.15
#: no points_to_sensor verdict on a sample with fewer raw points
MIN_PROJECTED = 16
#: image_size smaller than the image lidar2img projects into: at least SMALL_RATIO times more raw points
#: inside twice image_size than inside it (correct inputs: at most 1.18x), at least MIN_CORNER of them, and
#: every principal point in [SMALL_CENTRE, 1.5) of image_size (a centred one is at 0.5; half the size: 1.0)
SMALL_RATIO = 2.0
SMALL_CENTRE = 0.75
MIN_CORNER = 32


def points_in_voxels(points: Tensor, points_batch: Tensor, coords: Tensor, spatial_shape: Sequence[int],
                     batch_size: int, voxel_size: Sequence[float], point_range_min: Sequence[float],
                     stride: Sequence[int], point_range_max: Optional[Sequence[float]]) -> Tuple[Tensor, Tensor]:
    """``(on_grid (B,), in_voxel (B,))``: per sample, its raw points inside the grid at ``stride`` and those
    of them whose voxel is among its voxels. A sort of the voxel keys and a search of the point keys, the
    keys of :func:`~mssf_blocks.functional.geometry.voxel_centroids` (the same points meet the same voxels)."""
    shape = tuple(int(v) for v in spatial_shape)
    dtype = torch.float64 if points.dtype == torch.float64 else torch.float32
    voxel_keys = torch.sort(_grid_keys(coords, shape)).values
    point_keys = _point_keys(points.detach()[:, :3].to(dtype), points_batch, tuple(voxel_size), tuple(point_range_min),
                             None if point_range_max is None else tuple(point_range_max),
                             tuple(int(s) for s in stride), shape)
    on_grid = point_keys >= 0
    at = torch.searchsorted(voxel_keys, point_keys).clamp(max=max(voxel_keys.shape[0] - 1, 0))
    hit = on_grid & (voxel_keys[at] == point_keys) if voxel_keys.shape[0] else torch.zeros_like(on_grid)
    pb = points_batch.long()
    return (torch.bincount(pb[on_grid], minlength=batch_size), torch.bincount(pb[hit], minlength=batch_size))


def check_points_in_voxels(points: Tensor, points_batch: Tensor, coords: Tensor, batch_index: Tensor,
                           spatial_shape: Sequence[int], batch_size: int, voxel_size: Sequence[float],
                           point_range_min: Sequence[float], stride: Sequence[int],
                           point_range_max: Optional[Sequence[float]], has_points: Tensor) -> None:
    """Warn per sample when few of its on-grid raw points lie in its voxels, or when it has voxels and no
    points while others have some (see the module doc). Skips a sample whose voxels hold none of its
    points (:func:`._sanity.check_centroid_coverage` names that one)."""
    if coords.shape[0] == 0 or points.shape[0] == 0:
        return
    n_vox = torch.bincount(batch_index, minlength=batch_size)
    n_pts = torch.bincount(points_batch.long(), minlength=batch_size)
    n_hold = torch.bincount(batch_index[has_points], minlength=batch_size)
    for b in ((n_vox > 0) & (n_pts == 0)).nonzero().flatten().tolist():
        warnings.warn(MSSFGeometryWarning(
            f"points_batch: sample {b} has {int(n_vox[b])} voxels but none of the {points.shape[0]} points is "
            f"labelled {b} (points per sample: {n_pts.tolist()}); voxels are built from points, so points_batch "
            "does not match the voxels' batch index (all zeros? it is each point's sample index)"
        ), stacklevel=2)
    on_grid, in_voxel = points_in_voxels(points, points_batch, coords, spatial_shape, batch_size, voxel_size,
                                         point_range_min, stride, point_range_max)
    low = (on_grid >= MIN_POINTS) & (n_hold > 0) & (in_voxel < POINTS_IN_VOXELS_MIN * on_grid)
    for b in low.nonzero().flatten().tolist():
        k, n = int(in_voxel[b]), int(on_grid[b])
        warnings.warn(MSSFGeometryWarning(
            f"points: only {k} of sample {b}'s {n} raw points on the grid ({k / n:.2f}, expected about 1.0) lie "
            f"in one of its {int(n_vox[b])} voxels at stride {tuple(int(s) for s in stride)}: the voxels and the "
            "points disagree; check voxel_size (x, y, z order), the voxels' stride (SparseVoxels.stride: "
            "the stride of the block's input, not of its output), point_range_min, the coords order (batch, z, y, x) with "
            "spatial_shape (D, H, W), and points_batch"
        ), stacklevel=2)


def project_raw(points: Tensor, points_batch: Tensor, lidar2img: Tensor, image_size: Sequence[int],
                matrix: Optional[Tensor], eps: float) -> Tuple[Tensor, Tensor]:
    """``(uv (P, V, 2), inside (P, V))`` of the raw points mapped by ``matrix`` ``(B, 4, 4)`` (or not) and
    projected with ``lidar2img``: :func:`~mssf_blocks.functional.geometry.project_points` without gradients
    (``uv = -1`` behind the camera, ``inside`` its ``valid``)."""
    with torch.no_grad():
        proj = project_points(points, points_batch, lidar2img, image_size, matrix, eps)
    return proj.uv, proj.valid


def sensor_fractions(points: Tensor, points_batch: Tensor, lidar2img: Tensor, image_size: Sequence[int],
                     points_to_sensor: Tensor, inside: Tensor, batch_size: int, eps: float):
    """``(n (B,), with (B,), {alternative: (B,)})``: per sample its raw points and the fraction of them in
    the image with ``points_to_sensor`` (``inside``, the in-image mask with it), with its inverse, with none."""
    pb = points_batch.long()
    n = torch.bincount(pb, minlength=batch_size).double()

    def fraction(mask: Tensor) -> Tensor:
        return torch.bincount(pb[mask.any(1)], minlength=batch_size).double() / n.clamp(min=1)

    inverse = torch.linalg.inv(points_to_sensor.detach().double())
    return n, fraction(inside), {
        "its inverse": fraction(project_raw(points, points_batch, lidar2img, image_size, inverse, eps)[1]),
        "no points_to_sensor": fraction(project_raw(points, points_batch, lidar2img, image_size, None, eps)[1]),
    }


def check_points_to_sensor(points: Tensor, points_batch: Tensor, lidar2img: Tensor, image_size: Sequence[int],
                           points_to_sensor: Tensor, inside: Tensor, batch_size: int, eps: float) -> None:
    """Warn per sample when the inverse of ``points_to_sensor`` (or none) puts far more of its raw points in
    the image than ``points_to_sensor`` does (see the module doc)."""
    n, with_m, alternatives = sensor_fractions(points, points_batch, lidar2img, image_size, points_to_sensor,
                                               inside, batch_size, eps)
    for b in (n >= MIN_PROJECTED).nonzero().flatten().tolist():
        name, best = max(((k, float(v[b])) for k, v in alternatives.items()), key=lambda kv: kv[1])
        mine = float(with_m[b])
        if best >= INVERSE_RATIO * mine and best - mine >= MIN_GAIN:
            warnings.warn(MSSFGeometryWarning(
                f"points_to_sensor: with it, {mine:.2f} of sample {b}'s {int(n[b])} raw points project inside "
                f"the image; with {name}, {best:.2f}: is it the forward augmentation matrix? points_to_sensor "
                "maps the augmented points back to the sensor frame (the inverse of augmentation_matrix: "
                "torch.linalg.inv); pass none when the points are not augmented"
            ), stacklevel=2)


def check_image_size_small(uv: Tensor, inside: Tensor, lidar2img: Tensor, image_size: Sequence[int]) -> None:
    """Warn when far more raw points project inside a multiple of ``image_size`` than inside it and the
    principal point lands at the image's far corner: ``image_size`` smaller than the image ``lidar2img``
    projects into (e.g. images stored at half size with the calibration of the full ones; or a feature level's
    size, ``feats[0].shape[-2:]``, whose principal point lands at 2 or more: then the multiple is twice the
    principal point, the scale of the level). ``uv``, ``inside`` from :func:`project_raw` (``uv = -1`` behind
    the camera)."""
    h, w = (int(v) for v in image_size)
    centre = _relative_centre(lidar2img, h, w)
    # (a centred principal point is at 0.5: at c, image_size is about 1 / (2 c) of the image; up to 1.5 the
    # doubled size is compared, as always; beyond it (a quarter, a level's size) the size the centre implies)
    top = float(centre.max()) if centre.numel() else 0.0
    scale = 2.0 if top < 1.5 else 2.0 * top
    n_in = int(inside.sum())
    n_twice = int(((uv >= 0) & (uv <= scale)).all(-1).sum())
    if n_twice < MIN_CORNER or n_twice < SMALL_RATIO * n_in:
        return
    if bool((centre >= SMALL_CENTRE).all()) and (scale > 2.0 or bool((centre < 1.5).all())):
        big = "twice it" if scale == 2.0 else f"{scale:.3g} x it"
        warnings.warn(MSSFGeometryWarning(
            f"projection: {n_in} raw point projections fall inside image_size={(h, w)} but {n_twice} inside {big}, "
            f"and the principal point lands at {tuple(round(float(v), 2) for v in centre.reshape(-1, 2)[0])} "
            "of it: is image_size smaller than the image lidar2img projects into (e.g. half its size: images "
            "resized without updating lidar2img; or a feature level's size instead of the image's)?"
        ), stacklevel=2)
