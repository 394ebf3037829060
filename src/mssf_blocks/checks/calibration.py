"""Calibration against the image it is used with: images resized on disk while the calibration was kept.

A camera's principal point (where its optical axis meets the image) lies near the image centre (View-of-Delft's
at 0.99 / 1.03 x the centre of its 1936 x 1216 images, KITTI's at 0.99 / 0.98 x, measured on the frames in
``../shared/realdata``; a crop of the sensor moves it by some percent). Images
stored at half size with the full-size ``P2`` / ``lidar2img`` put it at about twice the centre, the far
corner; images stored larger than the calibration's, near the near corner. That is read from the matrix and
the image shape alone (CPU numbers, no tensor data, no host synchronisation), on the first call, for any
scene, and it does not depend on where the points fall. Crops move the principal point along one axis, so
the verdict needs both axes off-centre by the same side, by 1.2 x or more (resize factors of 0.8 and
below, 1.25 and above, are seen).
"""

from __future__ import annotations

import warnings
from typing import Sequence

import torch
from torch import Tensor

from mssf_blocks.checks.geometry import _principal_points
from mssf_blocks.errors import MSSFGeometryWarning

__all__: list = []

#: principal point over the image centre, both axes, beyond this (or below its inverse): a resized image
_RATIO = 1.2


def check_calibration_image_size(lidar2img: Tensor, image_hw: Sequence, name: str, where: str) -> None:
    """Warn (:class:`MSSFGeometryWarning`) when ``lidar2img`` ``(V, 3, 4)`` float64 projects into an image about
    ``r`` times (r >= 1.2 or <= 1 / 1.2, both axes) the ``image_hw`` ``(H, W)`` (or ``(V, 2)``) it is used with.
    ``name`` / ``where`` say which matrix and which image (for the message)."""
    hw = torch.as_tensor(image_hw, dtype=torch.float64).reshape(-1, 2)
    if hw.shape[0] not in (1, lidar2img.shape[0]) or bool((hw <= 0).any()):
        return
    pp = _principal_points(lidar2img[None])[0]  # (V, 2) u, v
    wh = hw.flip(-1).expand(pp.shape[0], 2)
    ratio = (pp + 0.5) / (wh / 2)  # 1 at the image centre (pixel centres at integers)
    for v in range(pp.shape[0]):
        rx, ry = (float(r) for r in ratio[v])
        big, small = rx >= _RATIO and ry >= _RATIO, rx <= 1 / _RATIO and ry <= 1 / _RATIO
        if not (big or small) or not (rx == rx and ry == ry):
            continue
        w, h = (int(s) for s in wh[v])
        scale = (rx + ry) / 2
        warnings.warn(MSSFGeometryWarning(
            f"{name}: images resized without updating the calibration (lidar2img / P2)? camera {v}'s principal "
            f"point lies at (u, v) = ({float(pp[v, 0]):.1f}, {float(pp[v, 1]):.1f}) px, {rx:.2f} x / {ry:.2f} x "
            f"the centre of the {w} x {h} image ({where}), where a camera's lies near 1 x: the calibration was "
            f"made for images about {scale:.2f} x this size. Store the images at the calibration's size, or scale "
            f"P2's first two rows (and lidar2img's) by the images' resize factor"
        ), stacklevel=4)
