"""A coverage fraction that collapses against its running value (``docs/conventions.md``, "Common mistakes").

The projector's coverage checks (:mod:`._sanity`) warn when a sample's coverage is *zero*. A mistake can
also cut it without zeroing it: the forward augmentation matrix passed as ``points_to_sensor`` doubles a
random rotation and turns most voxels out of view in some frames; mislabelled ``points_batch`` leaves a
sample with no points; a slightly wrong ``point_range_min`` makes only a few voxels hold their points.
:class:`RunningCoverage` keeps, per projector and per voxel stride, the running mean of each coverage
(projection: fraction of a sample's voxels inside the image; centroids: fraction holding a point) and
warns once when a sample falls below :data:`COLLAPSE_RATIO` of it.

It holds plain Python numbers, updated only where the checks already read the data back (CPU tensors,
or ``set_geometry_checks(True)``), so it adds no host synchronisation; it is not part of the module's
``state_dict`` (a loaded model starts a new warm-up).
"""

from __future__ import annotations

import warnings
from typing import Dict, List, Sequence, Tuple

from mssf_blocks.errors import MSSFGeometryWarning

#: samples (with at least MIN_SAMPLE_VOXELS voxels) seen before any verdict: the running value of a
#: new module, or of one that just loaded weights, means nothing yet
WARMUP_SAMPLES = 8
#: the running value is a mean over the first WINDOW samples, then an exponential mean with weight 1 / WINDOW
WINDOW = 32
#: warn when a sample's coverage is below this fraction of the running value. Correct training on the
#: generated VoD-like scenes (augmentation on) keeps every sample within 0.76-1.16 x its running value
#: (benchmarks/coverage_spread.py, docs/conventions.md); a quarter leaves room for real frames that vary
#: more (a scene with most returns beside the road), while a doubled +-pi/4 rotation or a point range one
#: voxel off falls far below it
COLLAPSE_RATIO = 0.25
#: no verdict on a sample with fewer voxels (a fraction of a handful is noise), or on a running value
#: below this (a module that hardly ever sees the camera has nothing to collapse from)
MIN_SAMPLE_VOXELS = 16
MIN_RUNNING = 0.05

_CAUSES = {
    "projection": (
        "usual causes: points_to_sensor in the wrong direction (the forward augmentation matrix instead of "
        "its inverse: the random rotation is doubled), lidar2img not updated for this sample's image "
        "augmentation (resize, crop, flip), image_size of another image, lidar2img of another sample or camera"
    ),
    "centroids": (
        "usual causes: points_batch not matching the voxels' batch index (a sample's points labelled as "
        "another's), points of another frame or sweep, point_range_min or voxel_size (x, y, z order) not the "
        "ones the voxels were built with, a wrong voxels' stride (SparseVoxels.stride)"
    ),
}
_WHAT = {"projection": ("in-image fraction", "project inside the image"),
         "centroids": ("centroid fraction", "hold any of its points")}


class RunningCoverage:
    """Running mean of a per-sample coverage fraction per ``(kind, stride)``; warns once per key on a collapse."""

    def __init__(self) -> None:
        self._state: Dict[Tuple[str, Tuple[int, ...]], List] = {}  # key -> [samples seen, mean, warned]

    def reset(self) -> None:
        """Forget the running values (a new dataset or camera set-up)."""
        self._state.clear()

    def running(self, kind: str, stride: Sequence[int]) -> Tuple[int, float]:
        """``(samples seen, running mean)`` of ``kind`` (``"projection"`` / ``"centroids"``) at ``stride``."""
        seen, mean, _ = self._state.get((kind, tuple(int(s) for s in stride)), [0, 0.0, False])
        return seen, mean

    def observe(self, kind: str, stride: Sequence[int], hits: Sequence[int], totals: Sequence[int],
                skip: Sequence[bool] = ()) -> None:
        """Per sample ``b``: ``hits[b]`` of ``totals[b]`` voxels covered; compare with the running value,
        warn on the first collapse, then update. ``skip[b]``: already warned as zero (no second verdict)."""
        key = (kind, tuple(int(s) for s in stride))
        state = self._state.setdefault(key, [0, 0.0, False])
        seen, mean, warned = state
        for b, (hit, total) in enumerate(zip(hits, totals)):
            if total < MIN_SAMPLE_VOXELS:
                continue
            frac = hit / total
            name, verb = _WHAT[kind]
            if (not warned and seen >= WARMUP_SAMPLES and mean >= MIN_RUNNING and frac < COLLAPSE_RATIO * mean
                    and not (b < len(skip) and skip[b])):
                warned = True
                warnings.warn(MSSFGeometryWarning(
                    f"{kind}: sample {b}'s {name} is {frac:.3f} ({hit} of {total} voxels {verb}), below "
                    f"{COLLAPSE_RATIO:g} x its running value {mean:.3f} (mean over the last ~{min(seen, WINDOW)} "
                    f"samples of this projector at stride {key[1]}); {_CAUSES[kind]}. (A real frame can do "
                    "this too: warned once per projector; the threshold is in docs/conventions.md)"
                ), stacklevel=3)
            seen += 1
            mean += (frac - mean) / min(seen, WINDOW)
        state[:] = [seen, mean, warned]
