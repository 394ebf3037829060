"""Checks across arguments and modules: which argument disagrees, and what torch's BatchNorm would refuse.

Both exist so that a mistake gets our error, naming the argument to change and both figures, before
torch's own (an ``image_features`` blamed for a ``lidar2img`` of the wrong batch; BatchNorm's
"Expected more than 1 value per channel"). Shapes and module flags only: no tensor data is read, no
host synchronisation, nothing to skip while a graph is captured.
"""

from __future__ import annotations

from collections import Counter
from typing import Any, Optional, Sequence, Tuple

from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

__all__ = ["check_agreement", "level_batch_entries", "check_batch_statistics", "batch_norm_in_training",
           "check_channels", "query_range_mismatch",
           "channels_last_hint"]

#: ``(name, size, shape)``: an argument, the size it gives (its batch size, its cameras...) and its shape (a
#: tuple, or its text)
Entry = Tuple[str, Optional[int], Any]


def _size(size: Any) -> Optional[int]:
    """``size`` when it is a plain int; ``None`` for a symbolic size (graph capture: not compared, no guard)."""
    return size if isinstance(size, int) else None


def _describe(entries: Sequence[Entry], what: str = "") -> str:
    return ", ".join(f"{name} {shape if isinstance(shape, str) else f'of shape {shape}'}"
                     + (f" ({what} {size})" if what else "") for name, size, shape in entries)


def check_agreement(entries: Sequence[Entry], what: str = "batch size",
                    reference: Optional[Tuple[str, int]] = None) -> None:
    """Every entry gives the same ``what``; else an error naming the argument(s) that disagree.

    With ``reference = (name, size)`` (e.g. the voxels' ``batch_size``) that size decides; without, the
    size most entries give, ties going to the earliest entry (list the most reliable first: image levels
    come out of a network run on the whole batch, a ``lidar2img`` is assembled by hand). The message
    names the disagreeing argument(s) with their shapes and what they disagree with, so both sides are
    named whichever is really wrong. Entries whose size is ``None`` are skipped.
    """
    entries = [e for e in entries if _size(e[1]) is not None]  # (symbolic sizes: not checked)
    if reference is not None:
        ref_name, expected = reference
        bad = [e for e in entries if e[1] != expected]
        if bad:
            raise MSSFError(
                f"{', '.join(e[0] for e in bad)}: expected {what} {expected} ({ref_name}), got "
                f"{_describe(bad, what)}; every one holds one entry per sample of the voxels' batch"
            )
        return
    counts = Counter(e[1] for e in entries)
    if len(counts) <= 1:
        return
    top = max(counts.values())
    expected = next(e[1] for e in entries if counts[e[1]] == top)
    good = [e for e in entries if e[1] == expected]
    bad = [e for e in entries if e[1] != expected]
    raise MSSFError(
        f"{', '.join(e[0] for e in bad)}: expected {what} {expected} (as {_describe(good)}), got "
        f"{_describe(bad, what)}; {' and '.join(e[0] for e in bad + good)} must agree on the {what}"
    )


def level_batch_entries(levels: Any, name: str = "image_features", dim: int = 0, ndims=(4, 5)) -> list:
    """Entries for :func:`check_agreement` of image levels (size ``shape[dim]`` of the ``ndims``-d ones): one
    (``name``) when the levels agree (they come out of one network run, so they vote once), one per level
    when they do not."""
    if isinstance(levels, Tensor) or not isinstance(levels, (list, tuple)):
        return []
    entries = [(f"{name}[{i}]", _size(lvl.shape[dim]), tuple(lvl.shape))
               for i, lvl in enumerate(levels) if isinstance(lvl, Tensor) and lvl.dim() in ndims]
    if len(entries) > 1 and len({e[1] for e in entries}) == 1:
        return [(name, entries[0][1], f"of shape {entries[0][2]} (level 0 of {len(entries)})")]
    return entries


def batch_norm_in_training(module: nn.Module) -> Optional[nn.Module]:
    """The first BatchNorm of ``module`` that takes batch statistics (training mode), or ``None``."""
    return next((m for m in module.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm) and m.training), None)


def check_batch_statistics(module: nn.Module, rows: Any, name: str, detail: str, owner: str) -> None:
    """Our error where a training-mode BatchNorm in ``module`` would get exactly one row (torch's
    "Expected more than 1 value per channel when training", which names no argument).

    ``rows``: the row count the norm gets (a symbolic size under graph capture is not checked: no guard
    is added); ``name``: the argument blamed; ``detail``: what was received (``"exactly one of the 5
    voxels is visible in the image"``); ``owner``: the module, for the message.
    """
    if not (isinstance(rows, int) and rows == 1):
        return
    bn = batch_norm_in_training(module)
    if bn is not None:
        raise MSSFError(
            f"{name}: {detail}, and {type(bn).__name__} in training mode ({owner}) cannot compute batch "
            "statistics from one row (expected at least 2 rows); train with more than one per batch (a larger "
            f"batch, or skip this frame), or put the {owner} in eval mode (.eval())"
        )


def check_channels(x: Any, name: str, channels: int, arg: str, dim: int = 1) -> None:
    """``x.shape[dim]`` (its channels) equals ``channels``, the constructor argument ``arg``
    (``"MSDFF embed_dim"``); else an error naming ``x``, ``arg`` and both numbers. Other dims and non-tensors
    are left to the shape checks that follow."""
    if isinstance(x, Tensor) and x.dim() > dim and x.shape[dim] != channels:
        got = x.shape[dim]
        fix = f"build it with {arg.split()[-1]}={got}, or pass {channels}-channel {name}" + channels_last_hint(
            x, channels, name)
        raise MSSFError(
            f"{name}: expected {channels} channels ({arg}={channels}), got shape {tuple(x.shape)} ({got} channels); "
            f"{fix}"
        )


def channels_last_hint(x: Tensor, channels: int, name: str) -> str:
    """For a channels-first map ``x`` ((B, C, H, W) or (B, V, C, H, W)) of the wrong width whose last dimension
    is the expected ``channels``: the permute that fixes a channels-last (NHWC) tensor, offered beside the width
    fix (the shape alone cannot tell an NHWC map from a width of ``channels``). ``""`` otherwise."""
    if x.dim() not in (4, 5) or x.shape[-1] != channels or x.shape[-3] == channels:
        return ""
    perm = "0, 3, 1, 2" if x.dim() == 4 else "0, 1, 4, 2, 3"
    return (f"; if it is channels-last (last dimension {channels}), pass {name}.permute({perm}) (channels-last "
            "memory is fine: torch.channels_last)")


def query_range_mismatch(point_cloud_range: Sequence[float], spatial_shape: Sequence[Any],
                         voxel_size: Sequence[float], point_range_min: Sequence[float],
                         stride: Sequence[int]) -> Optional[str]:
    """The warning's text when ``QueryInit``'s ``point_cloud_range`` is not the block's grid, else ``None``.

    The grid's range: ``point_range_min`` (within half a voxel) to its far corner ``point_range_min +
    spatial_shape * stride * voxel_size`` less at most two voxels at that stride (a padded shape: OpenPCDet's
    extra z cell, a strided convolution's rounding up). Another range (KITTI's copied beside a VoD grid)
    normalises every query position differently from what the range says, unseen; a warning, not an error,
    since any fixed affine normalisation still trains (it matters for weights trained with the grid's range,
    and for positions falling outside [0, 1]). Numbers only (a symbolic shape is not compared).
    """
    shape_zyx = [_size(s) for s in spatial_shape]
    if len(shape_zyx) != 3 or any(s is None for s in shape_zyx):
        return None
    cells, strides = shape_zyx[::-1], list(stride)[::-1]  # (x, y, z)
    lo, hi = point_cloud_range[:3], point_cloud_range[3:]
    far = [float(point_range_min[a]) + cells[a] * float(voxel_size[a]) * int(strides[a]) for a in range(3)]
    for a, axis in enumerate("xyz"):
        v = float(voxel_size[a]) * int(strides[a])
        tol = 1e-4 * max(1.0, abs(far[a]))
        if abs(lo[a] - float(point_range_min[a])) > 0.5 * float(voxel_size[a]) + tol or not (
                far[a] - 2 * v - tol <= hi[a] <= far[a] + tol):
            grid = tuple(round(float(m), 6) for m in point_range_min) + tuple(round(f, 6) for f in far)
            return (
                f"point_cloud_range: expected the block's grid, about {grid} (point_range_min, and "
                f"point_range_min + spatial_shape * stride * voxel_size in (x, y, z)), got "
                f"{tuple(point_cloud_range)} (QueryInit; axis {axis}: [{lo[a]}, {hi[a]}]): the query positions "
                "are normalised by another range; build QueryInit with the point-cloud range of the voxels' grid"
            )
    return None


def camera_batch_entries(inputs: Any) -> list:
    """Batch sizes of a :class:`~mssf_blocks.FusionInputs`' camera inputs (agreeing: FusionInputs checked
    them), as :func:`check_agreement` entries, for a voxel tensor's batch size to be checked against."""
    entries = level_batch_entries(inputs.image_features) + [
        ("lidar2img", inputs.lidar2img.shape[0], tuple(inputs.lidar2img.shape))]
    if inputs.points_to_sensor is not None and inputs.points_to_sensor.dim() == 3:  # (else the projector's shape error)
        entries.append(("points_to_sensor", inputs.points_to_sensor.shape[0], tuple(inputs.points_to_sensor.shape)))
    return entries


def check_input_agreement(image_features, lidar2img: Tensor, l2i: Tensor, points_to_sensor) -> None:
    """The batch size (and the cameras) of the camera inputs agree; else the error names the argument most
    of the others disagree with, with both shapes (shapes only). On a tie in the batch size the image levels
    win: they come out of a network run on the whole batch, while ``lidar2img`` / ``points_to_sensor`` are
    assembled by hand."""
    # (with several cameras a 4-d level is wrong whatever its batch, folded (B*V, C, H, W) most likely:
    # check_image_features says so, instead of a batch-size vote)
    ndims = (4, 5) if l2i.shape[1] == 1 else (5,)
    entries = level_batch_entries(image_features, ndims=ndims) + [("lidar2img", l2i.shape[0], tuple(lidar2img.shape))]
    if isinstance(points_to_sensor, Tensor) and points_to_sensor.dim() == 3:
        entries.append(("points_to_sensor", points_to_sensor.shape[0], tuple(points_to_sensor.shape)))
    check_agreement(entries, "batch size")
    # Cameras: lidar2img wins a tie (one matrix per camera of the set-up). 4-d levels are
    # one camera each: check_image_features names that case.
    check_agreement([("lidar2img", l2i.shape[1], tuple(lidar2img.shape))]
                    + level_batch_entries(image_features, dim=1, ndims=(5,)), "number of cameras V")


def check_visible_rows(norm: nn.Module, rows: int, n: int) -> None:
    """Our error, not BatchNorm's, for one visible voxel in training mode (the count is on the host already:
    ``nonzero`` read it). Every sampler's output stage goes through it."""
    check_batch_statistics(norm, rows, "projection", f"exactly one of the {n} voxels is visible in the image",
                           "fusion block")
