"""Global training augmentation of radar + camera samples, with the projection kept exact.

What the authors train with (``EricLiuhhh/MSSF``, VoxelNeXt ``n2m4`` VoD / TJ4D configurations, mmdet3d
``RandomFlip3D(flip_ratio_bev_horizontal=0.5)`` with its default ``sync_2d=True`` and
``GlobalRotScaleTrans(rot_range=[-pi/4, pi/4], scale_ratio_range=[0.95, 1.05])``), per sample and in
this order:

1. flip ``y -> -y`` with probability ``flip_prob`` (and, with ``sync_image_flip``, mirror the image on
   the same coin);
2. rotate about ``z`` by an angle drawn uniformly from ``rotation_range``;
3. scale by a factor drawn uniformly from ``scale_range``;
4. translate by a normal draw of std ``translation_std`` (the authors: 0).

The point matrix is :func:`mssf_blocks.augmentation_matrix` and its inverse goes into
``RadarCameraBatch.points_to_sensor``; the image flip is :func:`mssf_blocks.image_augmentation_matrix`
folded into ``lidar2img`` (:func:`mssf_blocks.apply_image_augmentation`), so every fusion block samples
the pixel the un-augmented point saw. GT boxes move with the points (centre, size times the scale, yaw).

Point features are transformed by meaning, one kind per column (:data:`FEATURE_KINDS`): ``x, y, z``
through the matrix; ``scalar`` columns (RCS, radial velocities, range, power, time) are kept;
``azimuth_rad`` / ``azimuth_deg`` (an angle measured like ``atan2(y, x)`` about the sensor, e.g.
TJ4DRadSet's Alpha once its convention is checked) are negated by the flip and shifted by the rotation;
``elevation`` is kept (a rotation about ``z``, the flip and a scaling do not change it). Translation
moves the points away from the sensor origin, so azimuth columns no longer match ``x, y`` after it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Iterable, Iterator, List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks import apply_image_augmentation, augmentation_matrix, image_augmentation_matrix
from mssf_blocks.errors import MSSFError

from .batch import RadarCameraBatch

__all__ = ["FEATURE_KINDS", "AugmentationConfig", "SampleAugmentation", "draw_augmentation", "augment_points",
           "augment_boxes", "augment_batch", "augment_batches", "NO_AUGMENTATION"]

#: Kinds a point column can have (see the module docstring).
FEATURE_KINDS = ("x", "y", "z", "scalar", "azimuth_rad", "azimuth_deg", "elevation")


@dataclass(frozen=True)
class AugmentationConfig:
    """Probabilities and ranges of the global augmentation (defaults: the authors' VoD / TJ4D configs).

    Attributes:
        flip_prob: probability of the ``y -> -y`` flip (mmdet3d ``flip_ratio_bev_horizontal``).
        sync_image_flip: mirror the image together with the points (mmdet3d ``sync_2d=True``, what the
            authors' configs do); ``False``: the image stays, only ``points_to_sensor`` undoes the flip
            (the paper's text: "no data augmentation is used for the input image").
        rotation_range: ``(low, high)`` radians about ``z``.
        scale_range: ``(low, high)`` global scale factor.
        translation_std: ``(x, y, z)`` metres, std of a normal translation.
        gt_range: optional ``(x0, y0, z0, x1, y1, z1)``: after augmenting, keep the GT boxes whose
            centre has ``x0 <= x < x1`` and ``y0 <= y < y1`` (mmdet3d ``ObjectRangeFilter``).
    """

    flip_prob: float = 0.5
    sync_image_flip: bool = True
    rotation_range: Tuple[float, float] = (-math.pi / 4, math.pi / 4)
    scale_range: Tuple[float, float] = (0.95, 1.05)
    translation_std: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    gt_range: Optional[Tuple[float, float, float, float, float, float]] = None

    def __post_init__(self) -> None:
        if not 0.0 <= self.flip_prob <= 1.0:
            raise MSSFError(f"flip_prob: expected a probability in [0, 1], got {self.flip_prob!r}")
        for name in ("rotation_range", "scale_range"):
            r = getattr(self, name)
            if len(r) != 2 or not all(math.isfinite(v) for v in r) or r[0] > r[1]:
                raise MSSFError(f"{name}: expected (low, high) finite with low <= high, got {r!r}")
        if max(abs(v) for v in self.rotation_range) > 2 * math.pi + 1e-9:
            raise MSSFError(f"rotation_range: expected radians (|angle| <= 2 pi), got {self.rotation_range!r}: "
                            "degrees? pass radians (e.g. (-math.pi / 4, math.pi / 4) for +-45 degrees)")
        if self.scale_range[0] <= 0:
            raise MSSFError(f"scale_range: expected positive factors, got {self.scale_range!r}")
        if len(self.translation_std) != 3 or any(not (math.isfinite(s) and s >= 0) for s in self.translation_std):
            raise MSSFError(f"translation_std: expected three stds >= 0, got {self.translation_std!r}")
        if self.gt_range is not None and len(self.gt_range) != 6:
            raise MSSFError(f"gt_range: expected (x0, y0, z0, x1, y1, z1), got {self.gt_range!r}")

    @property
    def is_identity(self) -> bool:
        """Whether every draw is the identity."""
        return (self.flip_prob == 0 and self.rotation_range == (0.0, 0.0) and self.scale_range == (1.0, 1.0)
                and all(s == 0 for s in self.translation_std))


#: No augmentation at all (flip probability 0, zero ranges).
NO_AUGMENTATION = AugmentationConfig(flip_prob=0.0, rotation_range=(0.0, 0.0), scale_range=(1.0, 1.0))


@dataclass(frozen=True)
class SampleAugmentation:
    """One sample's draw: ``p' = T + s * Rz(rotation) * F * p`` (``F``: ``y -> -y`` when ``flip``)."""

    flip: bool
    rotation: float
    scale: float
    translation: Tuple[float, float, float]
    image_flip: bool

    def point_matrix(self) -> Tensor:
        """``(4, 4)`` float64 forward matrix (:func:`mssf_blocks.augmentation_matrix`)."""
        return augmentation_matrix(flip_x=self.flip, rotation=self.rotation, scale=self.scale,
                                   translation=self.translation)


def draw_augmentation(config: AugmentationConfig, generator: torch.Generator) -> SampleAugmentation:
    """Draw one sample's augmentation from ``config`` with ``generator`` (always four draws, so the stream
    does not depend on the outcomes)."""
    u = torch.rand(3, generator=generator, dtype=torch.float64).tolist()
    t = torch.randn(3, generator=generator, dtype=torch.float64).tolist()
    flip = u[0] < config.flip_prob
    lo, hi = config.rotation_range
    s_lo, s_hi = config.scale_range
    return SampleAugmentation(
        flip=flip, rotation=lo + (hi - lo) * u[1], scale=s_lo + (s_hi - s_lo) * u[2],
        translation=tuple(float(a * b) for a, b in zip(t, config.translation_std)),
        image_flip=flip and config.sync_image_flip,
    )


def _check_kinds(kinds: Sequence[str], num_columns: int) -> Tuple[str, ...]:
    kinds = tuple(kinds)
    if len(kinds) != num_columns:
        raise MSSFError(f"feature_kinds: expected one kind per point column ({num_columns}), got {len(kinds)}: {kinds}")
    if kinds[:3] != ("x", "y", "z"):
        raise MSSFError(f"feature_kinds: expected ('x', 'y', 'z') first, got {kinds[:3]}")
    bad = [k for k in kinds[3:] if k not in FEATURE_KINDS[3:]]
    if bad:
        raise MSSFError(f"feature_kinds: expected kinds from {FEATURE_KINDS[3:]} after x, y, z, got {bad}")
    return kinds


def _wrap(angle: Tensor, half_turn: float) -> Tensor:
    """Angle into ``[-half_turn, half_turn)``."""
    return torch.remainder(angle + half_turn, 2 * half_turn) - half_turn


def augment_points(points: Tensor, aug: SampleAugmentation, feature_kinds: Sequence[str]) -> Tensor:
    """``(P, C)`` points augmented by ``aug``, every column by its kind (computed in float64).

    Args:
        points: ``(P, C)`` floating, ``x, y, z`` first.
        aug: the draw.
        feature_kinds: ``C`` kinds from :data:`FEATURE_KINDS`, ``("x", "y", "z", ...)``.

    Returns:
        ``(P, C)`` in the dtype of ``points``; ``scalar`` and ``elevation`` columns are the input's bits.
    """
    kinds = _check_kinds(feature_kinds, points.shape[1])
    m = aug.point_matrix().to(points.device)
    out = points.clone()
    out[:, :3] = (points[:, :3].double() @ m[:3, :3].T + m[:3, 3]).to(points.dtype)
    for col, kind in enumerate(kinds):
        if kind in ("azimuth_rad", "azimuth_deg"):
            half = math.pi if kind == "azimuth_rad" else 180.0
            a = points[:, col].double()
            a = (-a if aug.flip else a) + aug.rotation * half / math.pi
            out[:, col] = _wrap(a, half).to(points.dtype)
    return out


def augment_boxes(boxes: Tensor, aug: SampleAugmentation) -> Tensor:
    """``(G, 7+)`` boxes ``(x, y, z, dx, dy, dz, yaw, ...)`` moved with the points (float64 inside).

    Centre through the matrix, sizes times the scale, yaw negated by the flip then plus the rotation
    (wrapped to ``[-pi, pi)``); further columns are kept.
    """
    if boxes.dim() != 2 or boxes.shape[1] < 7:
        raise MSSFError(f"boxes: expected shape (G, 7+), got {tuple(boxes.shape)}")
    m = aug.point_matrix().to(boxes.device)
    b = boxes.double()
    out = b.clone()
    out[:, :3] = b[:, :3] @ m[:3, :3].T + m[:3, 3]
    out[:, 3:6] = b[:, 3:6] * aug.scale
    out[:, 6] = _wrap((-b[:, 6] if aug.flip else b[:, 6]) + aug.rotation, math.pi)
    return out.to(boxes.dtype)


def _flip_images(x: Tensor, flips: Tensor) -> Tensor:
    """``(B, ...)`` images or feature levels mirrored along the last axis where ``flips[b]``."""
    if not bool(flips.any()):
        return x
    return torch.where(flips.view(-1, *([1] * (x.dim() - 1))).to(x.device), torch.flip(x, [-1]), x)


def augment_batch(batch: RadarCameraBatch, feature_kinds: Sequence[str], config: AugmentationConfig,
                  generator: torch.Generator) -> Tuple[RadarCameraBatch, List[SampleAugmentation]]:
    """Augment every sample of ``batch`` independently (draws from ``generator`` in sample order).

    Points and GT boxes are transformed; ``points_to_sensor`` becomes the inverse of each sample's
    point matrix (composed with any ``points_to_sensor`` the batch already had); for samples whose image
    is flipped, the images (or every precomputed feature level: a level of stride ``s`` mirrors exactly
    like the image, see docs/conventions.md) are mirrored and ``lidar2img`` becomes ``A @ lidar2img``.

    Returns:
        ``(augmented batch, the draws)``.
    """
    if batch.image_size is None and config.sync_image_flip and config.flip_prob > 0:
        raise MSSFError("batch.image_size: required to flip the image (give images or image_size)")
    draws = [draw_augmentation(config, generator) for _ in range(batch.batch_size)]
    points = [augment_points(p, d, feature_kinds) for p, d in zip(batch.points, draws)]
    mats = torch.stack([d.point_matrix() for d in draws])
    inv = torch.linalg.inv(mats)
    if batch.points_to_sensor is not None:
        inv = batch.points_to_sensor.double().cpu() @ inv
    device = batch.lidar2img.device
    changes = dict(points=points, points_to_sensor=inv.to(device=device, dtype=batch.points[0].dtype))
    if batch.gt_boxes is not None:
        boxes = [augment_boxes(g, d) for g, d in zip(batch.gt_boxes, draws)]
        labels = list(batch.gt_labels)
        if config.gt_range is not None:
            x0, y0, _, x1, y1, _ = config.gt_range
            keep = [(g[:, 0] >= x0) & (g[:, 0] < x1) & (g[:, 1] >= y0) & (g[:, 1] < y1) for g in boxes]
            boxes, labels = [g[k] for g, k in zip(boxes, keep)], [lb[k] for lb, k in zip(labels, keep)]
        changes.update(gt_boxes=boxes, gt_labels=labels)
    flips = torch.tensor([d.image_flip for d in draws])
    if bool(flips.any()):
        a_flip, _ = image_augmentation_matrix(batch.image_size, flip=True)
        a = torch.where(flips[:, None, None], a_flip, torch.eye(3, dtype=torch.float64))
        changes["lidar2img"] = apply_image_augmentation(batch.lidar2img, a.to(device))
        if batch.images is not None:
            changes["images"] = _flip_images(batch.images, flips)
        if batch.image_features is not None:
            changes["image_features"] = [_flip_images(f, flips) for f in batch.image_features]
    return replace(batch, **changes), draws


def augment_batches(batches: Iterable[RadarCameraBatch], feature_kinds: Sequence[str],
                    config: AugmentationConfig, seed: int,
                    generator: Optional[torch.Generator] = None) -> Iterator[RadarCameraBatch]:
    """:func:`augment_batch` over a stream of batches with one generator seeded by ``seed``.

    Run it in the main process after the ``DataLoader`` (not in its workers): the draws then depend only
    on the seed and the batch order, whatever the number of workers. ``generator``: draw from this one
    instead (``seed`` ignored); its state after ``k`` batches is what a resumed run restores (the
    training CLI keeps it in its checkpoints), since the draws happen lazily, as batches are taken.
    """
    g = generator if generator is not None else torch.Generator().manual_seed(int(seed))
    for batch in batches:
        yield augment_batch(batch, feature_kinds, config, g)[0]


# --------------------------------------------------------------------------------------------------
# command-line options (the training CLI and the demo)
# --------------------------------------------------------------------------------------------------
def add_augmentation_arguments(parser) -> None:
    """Add ``--no-augment``, ``--flip-prob``, ``--sync-image-flip``, ``--rotation-range``, ``--scale-range``
    and ``--translation-std`` to an ``argparse`` parser; unset options take the recipe's values
    (:func:`augmentation_from_args`)."""
    import argparse

    g = parser.add_argument_group("augmentation (defaults: the dataset recipe, docs/training.md)")
    g.add_argument("--no-augment", action="store_true", help="train without any augmentation")
    g.add_argument("--flip-prob", type=float, default=None, metavar="P", help="probability of the y -> -y flip (0.5)")
    g.add_argument("--sync-image-flip", action=argparse.BooleanOptionalAction, default=None,
                   help="mirror the image with the points (default on, as the authors' configs)")
    g.add_argument("--rotation-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                   help="rotation about z, radians (-pi/4 pi/4)")
    g.add_argument("--scale-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                   help="global scale factor (0.95 1.05)")
    g.add_argument("--translation-std", type=float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="std of a normal translation, metres (0 0 0)")


def augmentation_from_args(args, base: AugmentationConfig, gt_range=None) -> AugmentationConfig:
    """The config the options of :func:`add_augmentation_arguments` ask for, over ``base``.

    Raises:
        MSSFError: for values :class:`AugmentationConfig` rejects (naming the field).
    """
    if getattr(args, "no_augment", False):
        return replace(NO_AUGMENTATION, gt_range=None if gt_range is None else tuple(gt_range))
    changes = {}
    for name in ("flip_prob", "sync_image_flip", "rotation_range", "scale_range", "translation_std"):
        v = getattr(args, name, None)
        if v is not None:
            changes[name] = tuple(v) if isinstance(v, list) else v
    if gt_range is not None:
        changes["gt_range"] = tuple(float(v) for v in gt_range)
    return replace(base, **changes)
