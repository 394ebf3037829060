"""KITTI calibration files: :class:`Calibration` (``P2``, ``R0_rect``, ``Tr_velo_to_cam`` -> ``lidar2img``).

Part of :mod:`mssf_examples.data.kitti_io` (which re-exports every public name).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from .kitti_points import PathLike

__all__ = ["Calibration", "parse_calibration", "read_calibration"]


@dataclass(frozen=True)
class Calibration:
    """KITTI calibration of one frame (float64).

    Attributes:
        P2: ``(3, 4)`` rectified camera projection.
        R0_rect: ``(3, 3)`` rectifying rotation (identity when the file has none).
        Tr_velo_to_cam: ``(3, 4)`` sensor (LiDAR or radar) to camera.
    """

    P2: Tensor
    R0_rect: Tensor
    Tr_velo_to_cam: Tensor

    @property
    def sensor_to_camera(self) -> Tensor:
        """``(4, 4)`` ``R0_rect(4x4) @ Tr_velo_to_cam(4x4)``: sensor to rectified camera frame."""
        r0 = torch.eye(4, dtype=torch.float64)
        r0[:3, :3] = self.R0_rect
        tr = torch.eye(4, dtype=torch.float64)
        tr[:3, :] = self.Tr_velo_to_cam
        return r0 @ tr

    @property
    def camera_to_sensor(self) -> Tensor:
        """``(4, 4)`` inverse of :attr:`sensor_to_camera`."""
        return torch.linalg.inv(self.sensor_to_camera)

    @property
    def lidar2img(self) -> Tensor:
        """``(3, 4)`` ``P2 @ R0_rect(4x4) @ Tr_velo_to_cam(4x4)``: sensor points to ``(u*d, v*d, d)``."""
        return self.P2 @ self.sensor_to_camera


_CALIB_KEYS = {
    "P2": ("P2",),
    "R0_rect": ("R0_rect", "R_rect", "R0"),
    "Tr_velo_to_cam": ("Tr_velo_to_cam", "Tr_velo_cam"),
}


def parse_calibration(text: str, source: str = "<calibration text>") -> Calibration:
    """Parse KITTI calibration text (``key: v1 v2 ...`` lines; keys with no values are ignored).

    ``R0_rect`` may be absent (identity); ``P2`` and ``Tr_velo_to_cam`` are required.
    """
    values: Dict[str, List[float]] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise MSSFError(f"{source}:{lineno}: expected 'key: values', got {line.strip()!r}")
        key, rest = line.split(":", 1)
        try:
            nums = [float(v) for v in rest.split()]
        except ValueError:
            raise MSSFError(f"{source}:{lineno}: expected numbers after {key!r}, got {rest.strip()!r}") from None
        if nums:
            values[key.strip()] = nums

    def get(name: str, size: int, required: bool) -> Optional[Tensor]:
        for alias in _CALIB_KEYS[name]:
            if alias in values:
                nums = values[alias]
                if len(nums) != size:
                    raise MSSFError(f"{source}: expected {size} values for {alias}, got {len(nums)}")
                return torch.tensor(nums, dtype=torch.float64)
        if required:
            raise MSSFError(f"{source}: expected a {name} line (3x4 = 12 values), found keys {sorted(values)}")
        return None

    p2 = get("P2", 12, True).reshape(3, 4)
    tr = get("Tr_velo_to_cam", 12, True).reshape(3, 4)
    r0 = get("R0_rect", 9, False)
    r0 = torch.eye(3, dtype=torch.float64) if r0 is None else r0.reshape(3, 3)
    return Calibration(P2=p2, R0_rect=r0, Tr_velo_to_cam=tr)


def read_calibration(path: PathLike) -> Calibration:
    """Read ``calib/<id>.txt``; see :func:`parse_calibration`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    return parse_calibration(path.read_text(), source=str(path))
