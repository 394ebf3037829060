"""Readers for KITTI-format radar/LiDAR detection datasets (View-of-Delft, TJ4DRadSet, KITTI).

What this module reads (see ``docs/real-data.md`` for the folder layouts):

* point clouds: ``velodyne/<id>.bin``, float32 little-endian ``N x C`` with ``C`` given by a
  :class:`PointFormat` (VoD radar 7, TJ4DRadSet radar 8, KITTI LiDAR 4);
* calibration: ``calib/<id>.txt`` (``P2``, ``R0_rect``, ``Tr_velo_to_cam``) -> ``lidar2img``
  ``= P2 @ R0_rect(4x4) @ Tr_velo_to_cam(4x4)`` (3 x 4, float64), the matrix the library's projector
  takes (OpenCV pixels, pixel ``i``'s centre at ``i``);
* labels: ``label_2/<id>.txt`` (KITTI object lines in the rectified camera frame), converted to the
  library's box convention ``(x, y, z, dx, dy, dz, yaw)`` in the sensor frame (z = box centre, yaw
  about +z, dx along the heading) and back;
* images: ``image_2/<id>.png|jpg`` as a ``(3, H, W)`` uint8 tensor (pillow).

The parts: :mod:`~mssf_examples.data.kitti_points` (point formats, point and image readers),
:mod:`~mssf_examples.data.kitti_calib` (calibration), :mod:`~mssf_examples.data.kitti_labels` (label files, class
lists), :mod:`~mssf_examples.data.kitti_boxes` (exact camera <-> sensor box conversion, corners, 2D boxes);
this module holds the frames and the dataset reader and re-exports every public name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from .kitti_boxes import (
    camera_box_corners,
    camera_box_corners_in_sensor,
    camera_boxes_to_sensor,
    points_in_image,
    project_boxes_2d,
    sensor_box_corners,
    sensor_boxes_to_camera,
    transform_points,
)
from .kitti_calib import Calibration, parse_calibration, read_calibration
from .kitti_labels import (
    KITTI_CLASSES,
    KNOWN_TYPES,
    TJ4D_CLASSES,
    VOD_CLASSES,
    KittiObjects,
    parse_labels,
    read_labels,
)
from .kitti_points import (
    KITTI_LIDAR,
    TJ4D_RADAR,
    VOD_RADAR,
    PathLike,
    PointFormat,
    _image_size,
    read_image,
    read_points,
)

__all__ = [
    "PointFormat",
    "VOD_RADAR",
    "TJ4D_RADAR",
    "KITTI_LIDAR",
    "VOD_CLASSES",
    "TJ4D_CLASSES",
    "KITTI_CLASSES",
    "Calibration",
    "parse_calibration",
    "read_calibration",
    "KittiObjects",
    "parse_labels",
    "read_labels",
    "read_points",
    "read_image",
    "camera_boxes_to_sensor",
    "sensor_boxes_to_camera",
    "camera_box_corners",
    "sensor_box_corners",
    "camera_box_corners_in_sensor",
    "transform_points",
    "project_boxes_2d",
    "points_in_image",
    "Frame",
    "FramePaths",
    "KittiFormatDataset",
    "frames_to_batch",
]


@dataclass
class Frame:
    """One frame of a KITTI-format dataset.

    Attributes:
        frame_id: the file stem, e.g. ``"00549"``.
        points: ``(P, F)`` float32 input features (``point_format.features``, x, y, z first).
        raw_points: ``(P, C)`` float32 all stored channels.
        point_format: the :class:`PointFormat` used.
        image: ``(3, H, W)`` uint8 RGB, or ``None`` when not loaded.
        image_size: ``(H, W)``.
        calib: the :class:`Calibration`.
        lidar2img: ``(3, 4)`` float64 sensor to pixel.
        objects: all label lines (camera frame), or ``None`` without labels.
        boxes: ``(G, 7)`` float64 sensor boxes for every label line (``DontCare`` too).
        labels: ``(G,)`` int64 index into ``class_names`` (-1 for other types).
        class_names: the evaluated classes.
    """

    frame_id: str
    points: Tensor
    raw_points: Tensor
    point_format: PointFormat
    image: Optional[Tensor]
    image_size: Tuple[int, int]
    calib: Calibration
    lidar2img: Tensor
    objects: Optional[KittiObjects]
    boxes: Tensor
    labels: Tensor
    class_names: Tuple[str, ...] = field(default=VOD_CLASSES)

    @property
    def gt_boxes(self) -> Tensor:
        """``(G', 7)`` boxes of the evaluated classes only."""
        return self.boxes[self.labels >= 0]

    @property
    def gt_labels(self) -> Tensor:
        """``(G',)`` 0-based labels of the evaluated classes only."""
        return self.labels[self.labels >= 0]


@dataclass(frozen=True)
class FramePaths:
    """Files of one frame (``image``/``label`` may be ``None`` when the folder does not exist)."""

    points: Path
    calib: Path
    image: Optional[Path]
    label: Optional[Path]


_IMAGE_EXTS = (".png", ".jpg", ".jpeg")


class KittiFormatDataset:
    """Locate and read frames of a KITTI-format dataset.

    Layouts (``S`` = ``sensor``; first match wins):

    * nested (VoD release): ``root/S/training/{velodyne,calib,image_2,label_2}``, ``root/S/ImageSets``;
    * standard (KITTI, TJ4DRadSet; ``sensor=None``): ``root/training/{...}``, ``root/ImageSets``;
    * flat: ``root/S/{velodyne,calib}`` (or ``root/{velodyne,calib}`` with ``sensor=None``) with
      ``image_2``/``label_2`` beside them or one level up (``../shared/realdata/vod`` uses
      ``radar/velodyne``, ``radar/calib``, ``image_2``, ``label_2``).

    ``split="test"`` reads ``testing/`` when it exists. Split files are ``ImageSets/<split>.txt`` beside
    ``training/`` (or in ``root/ImageSets``, or ``root/lidar/ImageSets`` as in the VoD release).

    Args:
        root: dataset root.
        point_format: :data:`VOD_RADAR`, :data:`TJ4D_RADAR`, :data:`KITTI_LIDAR` or your own.
        sensor: sub-folder (VoD: ``"radar"``, ``"radar_3frames"``, ``"radar_5frames"``, ``"lidar"``);
            ``None`` for roots holding ``training/`` or ``velodyne/`` directly.
        split: ``None`` (every point file) or the name of a split file (``"train"``, ``"val"``, ...).
        class_names: classes that get labels ``0..K-1``.
        load_image: read the image into :attr:`Frame.image` (otherwise only its size).

    Raises:
        FileNotFoundError: naming every path tried when the layout, a split file or a frame's file is
            missing.
    """

    def __init__(
        self,
        root: PathLike,
        point_format: PointFormat = VOD_RADAR,
        sensor: Optional[str] = "radar",
        split: Optional[str] = None,
        class_names: Sequence[str] = VOD_CLASSES,
        load_image: bool = True,
    ) -> None:
        if not isinstance(point_format, PointFormat):
            raise MSSFError(f"point_format: expected a PointFormat, got {type(point_format).__name__}")
        self.root = Path(root)
        self.point_format = point_format
        self.sensor = sensor
        self.split = split
        self.class_names = tuple(class_names)
        self.load_image = bool(load_image)
        if not self.root.is_dir():
            raise FileNotFoundError(f"dataset root not found: {self.root}")
        self.data_dir, self.layout = self._find_data_dir()
        search = [self.data_dir] if self.layout != "flat" else [self.data_dir, self.data_dir.parent]
        self.calib_dir = self._find_dir("calib", search, required=True)
        self.image_dir = self._find_dir("image_2", search, required=False)
        self.label_dir = self._find_dir("label_2", search, required=False)
        self.frame_ids = self._frame_ids()

    # -- layout ------------------------------------------------------------------------------------
    def _find_data_dir(self) -> Tuple[Path, str]:
        base = self.root / self.sensor if self.sensor else self.root
        subsets = ["testing", "training"] if self.split == "test" else ["training"]
        tried = []
        for subset in subsets:
            cand = base / subset
            tried.append(cand / "velodyne")
            if (cand / "velodyne").is_dir():
                return cand, "nested"
        tried.append(base / "velodyne")
        if (base / "velodyne").is_dir():
            return base, "flat"
        raise FileNotFoundError(
            f"no point-cloud folder for sensor={self.sensor!r} under {self.root}; tried: "
            + ", ".join(str(t) for t in tried)
        )

    @staticmethod
    def _find_dir(name: str, search: Sequence[Path], required: bool) -> Optional[Path]:
        for d in search:
            if (d / name).is_dir():
                return d / name
        if required:
            raise FileNotFoundError(f"no {name}/ folder; tried: " + ", ".join(str(d / name) for d in search))
        return None

    def _frame_ids(self) -> List[str]:
        points_dir = self.data_dir / "velodyne"
        available = sorted(p.stem for p in points_dir.glob("*.bin"))
        if self.split is None:
            return available
        cands = []
        # the VoD release keeps its split files in lidar/ImageSets only; OpenPCDet copies them per sensor
        for d in (self.data_dir.parent, self.data_dir, self.root, self.root / "lidar"):
            f = d / "ImageSets" / f"{self.split}.txt"
            if f not in cands:
                cands.append(f)
        for f in cands:
            if f.is_file():
                ids = [line.strip() for line in f.read_text().splitlines() if line.strip()]
                have = set(available)
                missing = [i for i in ids if i not in have]
                if missing:
                    raise FileNotFoundError(
                        f"split file {f} lists {len(missing)} frames without a point file in {points_dir}, "
                        f"e.g. {missing[:5]}"
                    )
                return ids
        raise FileNotFoundError(f"split file for split={self.split!r} not found; tried: " + ", ".join(map(str, cands)))

    # -- access --------------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.frame_ids)

    def __getitem__(self, index: int) -> Frame:
        return self.load(self.frame_ids[index])

    def paths(self, frame_id: str) -> FramePaths:
        """The files of ``frame_id`` (image/label ``None`` when their folder is absent)."""
        image = None
        if self.image_dir is not None:
            image = next((self.image_dir / f"{frame_id}{e}" for e in _IMAGE_EXTS
                          if (self.image_dir / f"{frame_id}{e}").is_file()), self.image_dir / f"{frame_id}.png")
        label = None if self.label_dir is None else self.label_dir / f"{frame_id}.txt"
        return FramePaths(points=self.data_dir / "velodyne" / f"{frame_id}.bin",
                          calib=self.calib_dir / f"{frame_id}.txt", image=image, label=label)

    def load(self, frame_id: str, with_labels: bool = True) -> Frame:
        """Read one frame.

        Args:
            frame_id: file stem.
            with_labels: read ``label_2`` (``False`` for test splits without labels: empty boxes).
        """
        frame_id = str(frame_id)
        p = self.paths(frame_id)
        raw = read_points(p.points, self.point_format)
        calib = read_calibration(p.calib)
        if p.image is None:
            raise FileNotFoundError(f"no image_2/ folder for frame {frame_id} (searched near {self.data_dir})")
        if not p.image.is_file():
            raise FileNotFoundError(f"image not found: {p.image.with_suffix('')}.{{png,jpg,jpeg}}")
        image = read_image(p.image) if self.load_image else None
        size = (int(image.shape[1]), int(image.shape[2])) if image is not None else _image_size(p.image)
        objects = None
        boxes = torch.zeros(0, 7, dtype=torch.float64)
        labels = torch.zeros(0, dtype=torch.long)
        if with_labels:
            if p.label is None:
                raise FileNotFoundError(f"no label_2/ folder for frame {frame_id} (searched near {self.data_dir}); "
                                        "use with_labels=False for unlabelled splits")
            objects = read_labels(p.label)
            unknown = [(k, n) for k, n in enumerate(objects.names, 1)
                       if n.lower() not in KNOWN_TYPES and n not in self.class_names]
            if unknown:
                k, n = unknown[0]
                raise MSSFError(f"{p.label}: line {k}: unknown object type {n!r} (the class names are "
                                f"{list(self.class_names)}; other known types of KITTI, VoD and TJ4DRadSet are "
                                "kept as not evaluated)")
            boxes = camera_boxes_to_sensor(objects.location, objects.dimensions, objects.rotation_y, calib)
            labels = torch.tensor([self.class_names.index(n) if n in self.class_names else -1
                                   for n in objects.names], dtype=torch.long)
        return Frame(
            frame_id=frame_id, points=self.point_format.select(raw), raw_points=raw,
            point_format=self.point_format, image=image, image_size=size, calib=calib,
            lidar2img=calib.lidar2img, objects=objects, boxes=boxes, labels=labels,
            class_names=self.class_names,
        )

    def __repr__(self) -> str:
        return (f"KittiFormatDataset(root={str(self.root)!r}, point_format={self.point_format.name}, "
                f"sensor={self.sensor!r}, split={self.split!r}, layout={self.layout!r}, frames={len(self)})")


def frames_to_batch(frames: Sequence[Frame], dtype: torch.dtype = torch.float32):
    """Stack frames into the examples' :class:`~mssf_examples.data.batch.RadarCameraBatch` (one camera).

    Points keep their input features (``Frame.points``); images become ``(B, 1, 3, H, W)`` floats in
    ``[0, 1]``; ``lidar2img`` is ``(B, 1, 3, 4)``; ground truth holds the evaluated classes only
    (:attr:`Frame.gt_boxes`, :attr:`Frame.gt_labels`). All images must have one size.
    """
    from .batch import RadarCameraBatch

    frames = list(frames)
    if not frames:
        raise MSSFError("frames: expected at least one Frame, got none")
    sizes = {f.image_size for f in frames}
    if len(sizes) != 1:
        raise MSSFError(f"frames: expected one image size to stack, got {sorted(sizes)}")
    if any(f.image is None for f in frames):
        raise MSSFError("frames: expected loaded images (KittiFormatDataset(load_image=True))")
    return RadarCameraBatch(
        points=[f.points.to(dtype) for f in frames],
        lidar2img=torch.stack([f.lidar2img for f in frames])[:, None].to(dtype),
        images=torch.stack([f.image for f in frames])[:, None].to(dtype) / 255.0,
        gt_boxes=[f.gt_boxes.to(dtype) for f in frames],
        gt_labels=[f.gt_labels for f in frames],
    )
