"""Pure functions of the semantic-guided head (paper Sec. III-E): focal loss and foreground labels.

* :func:`sigmoid_focal_loss` - the binary focal loss of Lin et al. (alpha 0.25, gamma 2) computed from
  logits, summed and normalised by the number of positives;
* :func:`points_in_boxes` - which points lie in which rotated 3D box ``(x, y, z, dx, dy, dz, yaw)``;
* :func:`voxel_foreground_labels` - the head's targets: a voxel is foreground when its centroid is in a
  ground-truth box of its own sample, ignored when it is only in the box enlarged by a margin.

Box convention: ``(x, y, z)`` is the box centre (``origin="center"``, as OpenPCDet and this library);
``origin="bottom"`` reads ``z`` as the centre of the bottom face (mmdetection3d's LiDAR boxes).
``dx`` is the extent along the heading, ``yaw`` is the rotation about ``+z`` (counter-clockwise seen
from above, 0 = heading along ``+x``).
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import (
    INDEX_DTYPES,
    check_dtype,
    check_finite,
    check_floating,
    check_index_range,
    check_shape,
)
from mssf_blocks.checks.geometry import check_boxes_frame, check_yaw_radians
from mssf_blocks.errors import MSSFError
from mssf_blocks.checks.boxes import check_boxes, check_margin, check_origin

__all__ = [
    "sigmoid_focal_loss",
    "points_in_boxes",
    "voxel_foreground_labels",
]

_REDUCTIONS = ("positives", "sum", "mean", "none")


def sigmoid_focal_loss(
    logits: Tensor,
    targets: Tensor,
    ignore: Optional[Tensor] = None,
    alpha: float = 0.25,
    gamma: float = 2.0,
    reduction: str = "positives",
) -> Tensor:
    """Binary focal loss from logits (Lin et al., 2017), as used to supervise the semantic head.

    Per element, with ``p = sigmoid(x)``, ``p_t = p t + (1 - p)(1 - t)`` and
    ``alpha_t = alpha t + (1 - alpha)(1 - t)``::

        loss = alpha_t * (1 - p_t) ** gamma * BCE_with_logits(x, t)

    The cross entropy is computed from the logits (``softplus``), never as ``log(sigmoid(x))``, so large
    logits give finite values and gradients.

    Args:
        logits: ``(N,)`` (or any shape) floating logits.
        targets: same shape, values in ``[0, 1]`` (0/1 labels; any float or bool dtype).
        ignore: optional bool mask of the same shape; ignored entries add nothing to the loss nor to the
            number of positives.
        alpha: weight of the positive class in ``[0, 1]``; a negative value disables the weighting
            (``alpha_t = 1``), as in torchvision.
        gamma: focusing exponent ``>= 0`` (``0`` gives the alpha-weighted cross entropy).
        reduction: ``"positives"`` (default): sum over the non-ignored entries divided by
            ``max(#positives, 1)`` where ``#positives`` is the sum of the non-ignored targets (their count
            for 0/1 labels); ``"sum"``; ``"mean"`` (over non-ignored entries, ``0`` when none);
            ``"none"``: the per-element loss (``0`` where ignored).

    Returns:
        A scalar (or the per-element loss for ``reduction="none"``) in the dtype of ``logits``; ``0``
        for empty input (still connected to ``logits`` so ``backward`` works).

    Example:
        >>> x = torch.tensor([0.0, 2.0]); t = torch.tensor([1.0, 0.0])
        >>> round(float(sigmoid_focal_loss(x, t)), 4)  # (0.25*0.5**2*ln2 + 0.75*sig(2)**2*softplus(2)) / 1
        1.2809
    """
    check_floating(check_finite(_tensor(logits, "logits"), "logits"), "logits")
    targets = _tensor(targets, "targets")
    if tuple(targets.shape) != tuple(logits.shape):
        raise MSSFError(
            f"targets: expected the shape of logits {tuple(logits.shape)}, got {tuple(targets.shape)}"
        )
    targets = targets.to(logits.dtype)
    if targets.numel():
        # one host synchronisation for the three checks (a GPU stalls on each read-back)
        finite, lo, hi = torch.stack([torch.isfinite(targets).all().to(targets.dtype), targets.min(),
                                      targets.max()]).tolist()
        if not finite:
            check_finite(targets, "targets")
        if lo < 0 or hi > 1:
            raise MSSFError(f"targets: expected values in [0, 1], got values in [{lo}, {hi}]")
    if ignore is not None:
        ignore = _tensor(ignore, "ignore")
        if tuple(ignore.shape) != tuple(logits.shape):
            raise MSSFError(
                f"ignore: expected a bool mask of the shape of logits {tuple(logits.shape)}, "
                f"got shape {tuple(ignore.shape)}"
            )
        check_dtype(ignore, "ignore", (torch.bool,))
    if not isinstance(alpha, (int, float)) or isinstance(alpha, bool) or alpha > 1 or alpha != alpha:
        raise MSSFError(f"alpha: expected a float in [0, 1] (or negative to disable), got {alpha!r}")
    if not isinstance(gamma, (int, float)) or isinstance(gamma, bool) or not gamma >= 0:
        raise MSSFError(f"gamma: expected a non-negative float, got {gamma!r}")
    if reduction not in _REDUCTIONS:
        raise MSSFError(f"reduction: expected one of {_REDUCTIONS}, got {reduction!r}")

    t = targets
    p = torch.sigmoid(logits)
    # softplus(x) - x t == BCE(sigmoid(x), t) without forming log(sigmoid(x)).
    ce = torch.nn.functional.binary_cross_entropy_with_logits(logits, t, reduction="none")
    p_t = p * t + (1 - p) * (1 - t)
    loss = ce * (1 - p_t) ** gamma if gamma != 0 else ce
    if alpha >= 0:
        loss = (alpha * t + (1 - alpha) * (1 - t)) * loss
    keep = None if ignore is None else ~ignore
    if keep is not None:
        # where (not multiply) so an inf/NaN can never leak out of an ignored entry.
        loss = torch.where(keep, loss, torch.zeros_like(loss))
    if reduction == "none":
        return loss
    total = loss.sum()
    if reduction == "sum":
        return total
    if reduction == "mean":
        count = logits.numel() if keep is None else int(keep.sum())
        return total / max(count, 1)
    positives = t.sum() if keep is None else (t * keep).sum()
    return total / positives.detach().clamp(min=1.0)


def _tensor(x, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise MSSFError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x


def points_in_boxes(
    points: Tensor,
    boxes: Tensor,
    origin: str = "center",
    margin: float = 0.0,
    eps: float = 1e-6,
) -> Tensor:
    """Which points lie inside which rotated 3D box (pure torch, any device).

    A point is inside box ``(x, y, z, dx, dy, dz, yaw)`` when its coordinates in the box frame
    (translated to the centre, rotated by ``-yaw`` about ``z``) satisfy
    ``|l_x| <= dx/2 + margin + eps``, ``|l_y| <= dy/2 + margin + eps`` and ``|l_z| <= dz/2 + margin + eps``
    (faces are inside; ``eps`` absorbs the rounding of the rotation so points exactly on a face are
    inside at every yaw). ``margin`` enlarges every face outwards by that many metres.

    Args:
        points: ``(P, 3+)`` floating ``x, y, z`` (further columns ignored).
        boxes: ``(G, 7+)`` floating ``(x, y, z, dx, dy, dz, yaw)`` (further columns, e.g. velocities,
            ignored). Sizes must be non-negative.
        origin: ``"center"`` - ``z`` is the box centre (this library, OpenPCDet); ``"bottom"`` - ``z`` is
            the bottom-face centre (mmdetection3d ``LiDARInstance3DBoxes``).
        margin: metres added to every face (``>= 0``).
        eps: tolerance in metres (``>= 0``).

    Returns:
        ``(P, G)`` bool. Memory is ``O(P G)``; split large point sets yourself.

    Example:
        >>> box = torch.tensor([[0.0, 0, 0, 4, 2, 2, 0]])
        >>> points_in_boxes(torch.tensor([[1.9, 0.9, 0.0], [2.1, 0.0, 0.0]]), box).flatten().tolist()
        [True, False]
    """
    check_shape(points, "points", ("P", None))
    check_floating(points, "points")
    if points.shape[1] < 3:
        raise MSSFError(f"points: expected shape (P, >=3) with x, y, z first, got {tuple(points.shape)}")
    check_finite(points[:, :3], "points[:, :3]")
    check_boxes(boxes, "boxes")
    check_origin(origin)
    margin = check_margin(margin, "margin")
    eps = check_margin(eps, "eps")
    if boxes.device != points.device:
        raise MSSFError(f"boxes: expected device {points.device} (of points), got {boxes.device}")
    check_yaw_radians(boxes, "boxes")
    return _inside(points, boxes, origin, margin, eps)


def _inside(points: Tensor, boxes: Tensor, origin: str, margin: float, eps: float) -> Tensor:
    """:func:`points_in_boxes` on checked inputs (:func:`voxel_foreground_labels` checks them once)."""
    dtype = torch.promote_types(points.dtype, boxes.dtype)
    p = points[:, :3].to(dtype)
    b = boxes[:, :7].to(dtype)
    centre = b[:, :3]
    if origin == "bottom":
        centre = centre + torch.stack([torch.zeros_like(b[:, 5]), torch.zeros_like(b[:, 5]), b[:, 5] / 2], 1)
    rel = p[:, None, :] - centre[None, :, :]  # (P, G, 3)
    cos, sin = torch.cos(b[:, 6]), torch.sin(b[:, 6])
    # Rotation by -yaw: the box frame's x axis is (cos, sin) in the sensor frame.
    lx = rel[..., 0] * cos + rel[..., 1] * sin
    ly = -rel[..., 0] * sin + rel[..., 1] * cos
    lz = rel[..., 2]
    half = b[:, 3:6] / 2 + (margin + eps)
    return (lx.abs() <= half[:, 0]) & (ly.abs() <= half[:, 1]) & (lz.abs() <= half[:, 2])


def voxel_foreground_labels(
    centroids: Tensor,
    batch_index: Tensor,
    gt_boxes: Sequence[Tensor],
    margin: float = 0.1,
    origin: str = "center",
) -> Tuple[Tensor, Tensor]:
    """Targets of the semantic-guided head for every voxel.

    * foreground (label 1): the centroid is inside a ground-truth box of its own sample;
    * ignored: not foreground, but inside some box of its sample enlarged by ``margin`` metres on every
      side (a boundary band where annotation noise makes the label unreliable);
    * background (label 0): everything else (also every voxel of a sample without boxes).

    Args:
        centroids: ``(N, 3+)`` floating ``x, y, z`` voxel centroids (e.g. ``CentroidProjection.centroid``).
        batch_index: ``(N,)`` integer sample of every voxel.
        gt_boxes: length-``B`` sequence of ``(G_b, 7+)`` boxes ``(x, y, z, dx, dy, dz, yaw)``; ``G_b`` may
            be 0.
        margin: metres added to every face for the ignore band (``0`` disables ignoring).
        origin: ``"center"`` or ``"bottom"``, see :func:`points_in_boxes`.

    Returns:
        ``labels (N,)`` in the dtype of ``centroids`` (0/1) and ``ignore (N,)`` bool (never set where
        ``labels == 1``).
    """
    check_shape(centroids, "centroids", ("N", None))
    check_floating(centroids, "centroids")
    if centroids.shape[1] < 3:
        raise MSSFError(f"centroids: expected shape (N, >=3), got {tuple(centroids.shape)}")
    check_shape(batch_index, "batch_index", (centroids.shape[0],))
    check_dtype(batch_index, "batch_index", INDEX_DTYPES)
    if isinstance(gt_boxes, Tensor) or not isinstance(gt_boxes, Sequence):
        raise MSSFError(
            f"gt_boxes: expected a list with one (G_b, 7) tensor per sample, got {type(gt_boxes).__name__}"
        )
    check_index_range(batch_index, "batch_index", len(gt_boxes), "len(gt_boxes)")
    margin = check_margin(margin, "margin")
    for i, boxes in enumerate(gt_boxes):
        check_boxes(boxes, f"gt_boxes[{i}]")
        check_yaw_radians(boxes, f"gt_boxes[{i}]")
    check_origin(origin)
    check_finite(centroids[:, :3], "points[:, :3]")  # (the name points_in_boxes gave it)
    check_boxes_frame(centroids, batch_index, gt_boxes, origin)
    n = centroids.shape[0]
    labels = torch.zeros(n, dtype=centroids.dtype, device=centroids.device)
    ignore = torch.zeros(n, dtype=torch.bool, device=centroids.device)
    xyz = centroids[:, :3].detach()
    b = batch_index.long()
    for i, boxes in enumerate(gt_boxes):
        rows = (b == i).nonzero().flatten()
        if rows.numel() == 0 or boxes.shape[0] == 0:
            continue
        boxes = boxes.to(xyz.device)
        inside = _inside(xyz[rows], boxes, origin, 0.0, 1e-6).any(dim=1)
        labels[rows] = inside.to(labels.dtype)
        if margin > 0:
            near = _inside(xyz[rows], boxes, origin, margin, 1e-6).any(dim=1)
            ignore[rows] = near & ~inside
    return labels, ignore
