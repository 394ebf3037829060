"""KITTI-format point clouds and images: :class:`PointFormat` (VoD, TJ4DRadSet, KITTI layouts) and readers.

Part of :mod:`mssf_examples.data.kitti_io` (which re-exports every public name).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Tuple, Union

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

__all__ = ["PointFormat", "VOD_RADAR", "TJ4D_RADAR", "KITTI_LIDAR", "read_points", "read_image"]

PathLike = Union[str, Path]


@dataclass(frozen=True)
class PointFormat:
    """Channel layout of a ``velodyne/<id>.bin`` file and the input features a detector uses.

    Args:
        name: a label for messages.
        channels: names of the ``C`` float32 columns stored in the file, ``x, y, z`` first.
        features: the columns (by name, in order) that form the network input; ``x, y, z`` first.
    """

    name: str
    channels: Tuple[str, ...]
    features: Tuple[str, ...]

    def __post_init__(self) -> None:
        if tuple(self.channels[:3]) != ("x", "y", "z"):
            raise MSSFError(f"channels: expected x, y, z first, got {self.channels}")
        if tuple(self.features[:3]) != ("x", "y", "z"):
            raise MSSFError(f"features: expected x, y, z first, got {self.features}")
        missing = [f for f in self.features if f not in self.channels]
        if missing:
            raise MSSFError(f"features: expected names from channels {self.channels}, got unknown {missing}")

    @property
    def num_channels(self) -> int:
        return len(self.channels)

    @property
    def feature_index(self) -> List[int]:
        return [self.channels.index(f) for f in self.features]

    def select(self, raw: Tensor) -> Tensor:
        """``(P, C)`` raw columns -> ``(P, F)`` input features."""
        return raw[:, self.feature_index]


#: View-of-Delft radar (``radar``, ``radar_3frames``, ``radar_5frames``): the paper uses all 7 channels.
VOD_RADAR = PointFormat(
    "vod_radar",
    ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time"),
    ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time"),
)
#: TJ4DRadSet radar. The paper's input is ``[x, y, z, v_rc, Power]``; the files hold only the raw radial
#: velocity ``V_r`` and no ego-motion to compensate it, so ``v_r`` stands in for ``v_rc``. Define your
#: own :class:`PointFormat` with a compensated column when you have one.
TJ4D_RADAR = PointFormat(
    "tj4d_radar",
    ("x", "y", "z", "v_r", "range", "power", "alpha", "beta"),
    ("x", "y", "z", "v_r", "power"),
)
#: KITTI LiDAR (HDL-64): ``x, y, z, reflectance``.
KITTI_LIDAR = PointFormat("kitti_lidar", ("x", "y", "z", "reflectance"), ("x", "y", "z", "reflectance"))


def read_points(path: PathLike, point_format: PointFormat) -> Tensor:
    """Read a float32 little-endian ``N x C`` point file.

    Returns:
        ``(P, C)`` float32 tensor with the columns of ``point_format.channels``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point file not found: {path}")
    data = np.fromfile(path, dtype="<f4")
    c = point_format.num_channels
    if data.size % c:
        raise MSSFError(
            f"{path}: expected a multiple of {c} float32 values ({point_format.name}: {point_format.channels}), "
            f"got {data.size} values ({path.stat().st_size} bytes): truncated, damaged, or another dataset's "
            "point format"
        )
    _check_layout(path, data, point_format)
    return torch.from_numpy(data.reshape(-1, c).astype(np.float32))


def _check_layout(path: Path, data: np.ndarray, point_format: PointFormat) -> None:
    """For the formats defined here: when the values also make whole rows of another one, its columns
    must not fit better (:mod:`~mssf_examples.data.point_layout`; e.g. 8 k VoD points are 7 k TJ4DRadSet
    rows). A format of your own is checked by its size only."""
    known = (VOD_RADAR, TJ4D_RADAR, KITTI_LIDAR)
    others = [f for f in known if f != point_format and data.size % f.num_channels == 0]
    if point_format not in known or not others:
        return
    from .point_layout import read_layouts  # (it imports this module)

    mine, *rest = read_layouts(data, [point_format, *others])
    better = [r for r in rest if r.plausible]
    if better and not mine.plausible:
        raise MSSFError(f"{path}: point_format {point_format.name} does not fit the values, "
                        f"{better[0].point_format.name} does (as {mine.describe()}; as {better[0].describe()}): "
                        f"another dataset's point file? pass point_format={better[0].point_format.name.upper()}")


def read_image(path: PathLike) -> Tensor:
    """Read an image as a ``(3, H, W)`` uint8 RGB tensor (needs pillow)."""
    try:
        from PIL import Image
    except ImportError as exc:  # pragma: no cover - pillow is in the examples extra
        raise ImportError("reading images needs pillow: pip install 'mssf-blocks[examples]'") from exc
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    with Image.open(path) as im:
        arr = np.asarray(im.convert("RGB"), dtype=np.uint8)
    return torch.from_numpy(arr.copy()).permute(2, 0, 1).contiguous()


def _image_size(path: Path) -> Tuple[int, int]:
    from PIL import Image

    with Image.open(path) as im:
        w, h = im.size
    return int(h), int(w)
