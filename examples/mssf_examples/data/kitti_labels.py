"""KITTI label files: :class:`KittiObjects` (``label_2`` lines, rectified camera frame) and the class lists.

Part of :mod:`mssf_examples.data.kitti_io` (which re-exports every public name).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from .kitti_points import PathLike

__all__ = ["VOD_CLASSES", "TJ4D_CLASSES", "KITTI_CLASSES", "KNOWN_TYPES", "KittiObjects", "parse_labels", "read_labels"]

#: Evaluated classes (0-based labels in this order; any other type gets label -1).
VOD_CLASSES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
TJ4D_CLASSES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist", "Truck")
KITTI_CLASSES: Tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
#: Object types (lower case) of KITTI, View-of-Delft and TJ4DRadSet label files; a type outside these
#: and the dataset's class names is refused by the loader (a typo, another dataset's labels).
KNOWN_TYPES = frozenset(t.lower() for t in (
    "Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc", "DontCare",  # KITTI
    "rider", "bicycle", "unused_bicycle", "bicycle_rack", "human_depiction", "moped_scooter", "motor",  # VoD
    "ride_other", "ride_uncertain", "vehicle_other",
    "Bus", "Motorcyclist", "Tricyclist",  # other radar datasets' road users
))


@dataclass(frozen=True)
class KittiObjects:
    """The objects of one ``label_2`` file, in the rectified camera frame (G objects).

    Attributes:
        names: ``G`` type strings as written (``Car``, ``Cyclist``, ``DontCare``, ``bicycle``...).
        truncation: ``(G,)`` float64.
        occlusion: ``(G,)`` int64.
        alpha: ``(G,)`` float64 observation angle.
        boxes_2d: ``(G, 4)`` float64 ``(left, top, right, bottom)`` pixels.
        dimensions: ``(G, 3)`` float64 ``(h, w, l)`` metres (file order).
        location: ``(G, 3)`` float64 bottom-face centre in the camera frame.
        rotation_y: ``(G,)`` float64 rotation about camera Y.
        score: ``(G,)`` float64 16th column when present (VoD writes 1), else ``None``.
    """

    names: List[str]
    truncation: Tensor
    occlusion: Tensor
    alpha: Tensor
    boxes_2d: Tensor
    dimensions: Tensor
    location: Tensor
    rotation_y: Tensor
    score: Optional[Tensor] = None

    def __len__(self) -> int:
        return len(self.names)


def parse_labels(text: str, source: str = "<label text>") -> KittiObjects:
    """Parse KITTI label lines (15 fields, or 16 with a score)."""
    rows, names, scores = [], [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        f = line.split()
        if not f:
            continue
        if len(f) not in (15, 16):
            raise MSSFError(f"{source}:{lineno}: expected 15 or 16 fields in a KITTI label line, got {len(f)}")
        try:
            nums = [float(v) for v in f[1:15]]
            if len(f) == 16:
                scores.append(float(f[15]))
        except ValueError:
            raise MSSFError(f"{source}:{lineno}: expected numbers after the type, got {line.strip()!r}") from None
        names.append(f[0])
        rows.append(nums)
    if scores and len(scores) != len(rows):
        raise MSSFError(f"{source}: expected a score on every line or on none, got {len(scores)} of {len(rows)}")
    t = torch.tensor(rows, dtype=torch.float64).reshape(-1, 14)
    return KittiObjects(
        names=names,
        truncation=t[:, 0].clone(),
        occlusion=t[:, 1].round().long(),
        alpha=t[:, 2].clone(),
        boxes_2d=t[:, 3:7].clone(),
        dimensions=t[:, 7:10].clone(),
        location=t[:, 10:13].clone(),
        rotation_y=t[:, 13].clone(),
        score=torch.tensor(scores, dtype=torch.float64) if scores else None,
    )


def read_labels(path: PathLike) -> KittiObjects:
    """Read ``label_2/<id>.txt``; see :func:`parse_labels`."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"label file not found: {path}")
    return parse_labels(path.read_text(), source=str(path))
