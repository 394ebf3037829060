"""Write KITTI-format label / prediction files and whole VoD-layout trees.

* :func:`kitti_lines` turns sensor-frame boxes ``(x, y, z, dx, dy, dz, yaw)`` (z = box centre) into
  KITTI object lines in the rectified camera frame, the format of ``label_2`` and of the prediction files
  the official View-of-Delft / KITTI evaluation reads::

      type truncated occluded alpha left top right bottom h w l x y z rotation_y [score]

  with ``(x, y, z)`` the bottom-face centre, ``(h, w, l) = (dz, dy, dx)`` and ``rotation_y`` from the
  exact inverse conversion :func:`~mssf_examples.data.kitti_io.sensor_boxes_to_camera`; ``alpha =
  rotation_y - atan2(x_c, z_c)`` (``x_c, z_c`` the camera-frame box centre) wrapped to ``(-pi, pi]``; the
  2D box is :func:`image_boxes_2d`: the image extent of the camera-upright box (the solid the line
  describes), cut at the camera's near plane and clipped to ``[0, W - 1] x [0, H - 1]``.
  :func:`kitti_objects` gives the same objects as a :class:`~mssf_examples.data.kitti_io.KittiObjects`.
* :func:`write_vod_tree` saves generated :class:`~mssf_examples.scenes.synthetic.Scene` s as a View-of-Delft
  release tree (``<root>/<sensor>/training/{velodyne,calib,image_2,label_2}``, ``<root>/<sensor>/ImageSets``)
  that :class:`~mssf_examples.data.kitti_io.KittiFormatDataset` and the CLI read like the real download.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Dict, List, Mapping, Optional, Sequence, Union

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from .kitti_io import (
    Calibration,
    KittiObjects,
    camera_box_corners,
    sensor_boxes_to_camera,
)

__all__ = ["image_boxes_2d", "kitti_objects", "kitti_lines", "write_kitti_file", "calibration_text",
           "scene_calibration", "write_vod_tree"]

PathLike = Union[str, Path]


def _wrap(a: Tensor) -> Tensor:
    """Angles to ``(-pi, pi]``."""
    out = torch.remainder(a + math.pi, 2 * math.pi) - math.pi
    return torch.where(out <= -math.pi, out + 2 * math.pi, out)


#: The 12 edges of the :func:`~mssf_examples.data.kitti_io.camera_box_corners` ordering (bottom, top, verticals).
_EDGES = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                       [0, 4], [1, 5], [2, 6], [3, 7]])


def image_boxes_2d(corners: Tensor, P2: Tensor, image_size: Sequence[int], near: float = 1e-3) -> Tensor:
    """Image extent of boxes given by their camera-frame corners, clipped to the image.

    A box with every corner in front of the camera (depth ``> near``) gets the enclosing rectangle of its
    8 projected corners. A box that reaches behind the camera is first cut at the plane ``depth = near``:
    the corners in front plus the points where its 12 edges cross that plane; those crossings project
    far outside the image, so the box reaches the image border on the side where the object leaves the
    view -- what an annotator's 2D box of a truncated object shows. The rectangle is clipped to
    ``left, right in [0, W - 1]``, ``top, bottom in [0, H - 1]`` (KITTI / VoD labels). A box entirely
    behind the camera is not in the image: ``(0, 0, 0, 0)``.

    Args:
        corners: ``(G, 8, 3)`` corners in the rectified camera frame (:func:`~mssf_examples.data.kitti_io.camera_box_corners`).
        P2: ``(3, 4)`` rectified camera projection.
        image_size: ``(H, W)``.
        near: depth of the cutting plane in metres (``> 0``).

    Returns:
        ``(G, 4)`` float64 ``(left, top, right, bottom)``.
    """
    if not isinstance(corners, Tensor) or corners.dim() != 3 or tuple(corners.shape[1:]) != (8, 3):
        got = tuple(corners.shape) if isinstance(corners, Tensor) else type(corners).__name__
        raise MSSFError(f"corners: expected shape (G, 8, 3), got {got}")
    if not near > 0:
        raise MSSFError(f"near: expected a positive depth, got {near}")
    h, w = (int(v) for v in image_size)
    p = P2.to(torch.float64).reshape(3, 4)
    pts = corners.to(torch.float64)
    g = pts.shape[0]
    depth = pts @ p[2, :3] + p[2, 3]                                   # (G, 8)
    a, b = pts[:, _EDGES[:, 0]], pts[:, _EDGES[:, 1]]                  # (G, 12, 3)
    da, db = depth[:, _EDGES[:, 0]], depth[:, _EDGES[:, 1]]
    crosses = (da > near) != (db > near)
    t = ((da - near) / torch.where(crosses, da - db, torch.ones_like(da))).clamp(0, 1)
    cut = a + t[..., None] * (b - a)                                   # on the plane where crosses
    cand = torch.cat([pts, cut], dim=1)                                # (G, 20, 3)
    keep = torch.cat([depth > near, crosses], dim=1)
    hom = cand @ p[:, :3].T + p[:, 3]
    d = torch.where(keep, hom[..., 2], torch.ones_like(hom[..., 2]))
    uv = hom[..., :2] / d[..., None]
    big = torch.tensor(float("inf"), dtype=torch.float64)
    lo = torch.where(keep[..., None], uv, big).amin(dim=1)
    hi = torch.where(keep[..., None], uv, -big).amax(dim=1)
    boxes = torch.cat([lo, hi], dim=1)
    boxes[:, [0, 2]] = boxes[:, [0, 2]].clamp(0, w - 1)
    boxes[:, [1, 3]] = boxes[:, [1, 3]].clamp(0, h - 1)
    visible = keep.any(dim=1) if g else torch.zeros(0, dtype=torch.bool)
    return torch.where(visible[:, None], boxes, torch.zeros_like(boxes))


def kitti_objects(
    boxes: Tensor,
    labels: Tensor,
    class_names: Sequence[str],
    calib: Calibration,
    image_size: Sequence[int],
    scores: Optional[Tensor] = None,
    truncated: float = -1.0,
    occluded: int = -1,
    names: Optional[Sequence[str]] = None,
) -> KittiObjects:
    """Sensor-frame boxes as the KITTI objects of a label / prediction file (see :func:`kitti_lines`).

    Args:
        boxes: ``(K, 7)`` sensor boxes ``(x, y, z, dx, dy, dz, yaw)``, z = box centre.
        labels: ``(K,)`` indices into ``class_names`` (ignored where ``names`` is given).
        class_names: the type string of each label.
        calib: the frame's :class:`~mssf_examples.data.kitti_io.Calibration`.
        image_size: ``(H, W)`` of the frame's image (the 2D boxes are clipped to it).
        scores: ``(K,)`` detection scores, or ``None`` (labels).
        truncated, occluded: the value of every object (predictions: ``-1``, which KITTI kits ignore).
        names: optional ``K`` type strings overriding ``class_names[labels]`` (e.g. ``"DontCare"``).

    Returns:
        :class:`~mssf_examples.data.kitti_io.KittiObjects` (float64, camera frame).
    """
    if not isinstance(boxes, Tensor) or boxes.dim() != 2 or boxes.shape[1] != 7:
        got = tuple(boxes.shape) if isinstance(boxes, Tensor) else type(boxes).__name__
        raise MSSFError(f"boxes: expected shape (K, 7), got {got}")
    k = boxes.shape[0]
    if names is None:
        if not isinstance(labels, Tensor) or tuple(labels.shape) != (k,):
            got = tuple(labels.shape) if isinstance(labels, Tensor) else type(labels).__name__
            raise MSSFError(f"labels: expected shape ({k},) to match boxes, got {got}")
        bad = [int(v) for v in labels.tolist() if not 0 <= int(v) < len(class_names)]
        if bad:
            raise MSSFError(f"labels: expected values in [0, {len(class_names)}) (class_names {tuple(class_names)}), "
                            f"got {bad[:5]}")
        names = [class_names[int(v)] for v in labels.tolist()]
    elif len(names) != k:
        raise MSSFError(f"names: expected {k} strings to match boxes, got {len(names)}")
    if scores is not None and (not isinstance(scores, Tensor) or tuple(scores.shape) != (k,)):
        got = tuple(scores.shape) if isinstance(scores, Tensor) else type(scores).__name__
        raise MSSFError(f"scores: expected shape ({k},) to match boxes, got {got}")
    f64 = dict(dtype=torch.float64)
    if k == 0:
        return KittiObjects(names=[], truncation=torch.zeros(0, **f64), occlusion=torch.zeros(0, dtype=torch.long),
                            alpha=torch.zeros(0, **f64), boxes_2d=torch.zeros(0, 4, **f64),
                            dimensions=torch.zeros(0, 3, **f64), location=torch.zeros(0, 3, **f64),
                            rotation_y=torch.zeros(0, **f64),
                            score=None if scores is None else torch.zeros(0, **f64))
    loc, hwl, ry = sensor_boxes_to_camera(boxes.detach().cpu(), calib)
    centre_cam = loc - torch.stack([torch.zeros_like(hwl[:, 0]), hwl[:, 0] / 2, torch.zeros_like(hwl[:, 0])], 1)
    alpha = _wrap(ry - torch.atan2(centre_cam[:, 0], centre_cam[:, 2]))
    box2d = image_boxes_2d(camera_box_corners(loc, hwl, ry), calib.P2, image_size)
    return KittiObjects(names=list(names), truncation=torch.full((k,), float(truncated), **f64),
                        occlusion=torch.full((k,), int(occluded), dtype=torch.long), alpha=alpha, boxes_2d=box2d,
                        dimensions=hwl, location=loc, rotation_y=ry,
                        score=None if scores is None else scores.detach().cpu().to(torch.float64))


def kitti_lines(
    boxes: Tensor,
    labels: Tensor,
    class_names: Sequence[str],
    calib: Calibration,
    image_size: Sequence[int],
    scores: Optional[Tensor] = None,
    truncated: float = -1.0,
    occluded: int = -1,
    names: Optional[Sequence[str]] = None,
) -> List[str]:
    """KITTI object lines for sensor-frame boxes.

    Args:
        boxes: ``(K, 7)`` sensor boxes ``(x, y, z, dx, dy, dz, yaw)``, z = box centre.
        labels: ``(K,)`` indices into ``class_names`` (ignored where ``names`` is given).
        class_names: the type string of each label.
        calib: the frame's :class:`~mssf_examples.data.kitti_io.Calibration`.
        image_size: ``(H, W)`` of the frame's image (the 2D boxes are clipped to it, :func:`image_boxes_2d`).
        scores: ``(K,)`` detection scores, written as a 16th column; ``None`` writes 15 columns (labels).
        truncated, occluded: written as is (predictions: ``-1``, the value KITTI kits ignore).
        names: optional ``K`` type strings overriding ``class_names[labels]`` (e.g. ``"DontCare"``).

    Returns:
        ``K`` strings without newline.
    """
    obj = kitti_objects(boxes, labels, class_names, calib, image_size, scores=scores, truncated=truncated,
                        occluded=occluded, names=names)
    lines = []
    for i in range(len(obj)):
        nums = [float(obj.alpha[i]), *obj.boxes_2d[i].tolist(), *obj.dimensions[i].tolist(),
                *obj.location[i].tolist(), float(obj.rotation_y[i])]
        line = f"{obj.names[i]} {truncated:.2f} {int(occluded)} " + " ".join(f"{v:.6f}" for v in nums)
        if scores is not None:
            line += f" {float(scores[i]):.9g}"  # float32 scores exactly: the order (and ties) survive
        lines.append(line)
    return lines


def write_kitti_file(path: PathLike, lines: Sequence[str]) -> Path:
    """Write ``lines`` (one object each) to ``path``; an empty file when there are none."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(line + "\n" for line in lines))
    return path


def calibration_text(P2: Tensor, Tr_velo_to_cam: Tensor, R0_rect: Optional[Tensor] = None) -> str:
    """A KITTI ``calib/<id>.txt`` (``P0..P3`` = ``P2`` as in VoD, ``R0_rect``, ``Tr_velo_to_cam``), 17 digits."""
    fmt = lambda t: " ".join(format(float(v), ".17g") for v in t.reshape(-1).tolist())  # noqa: E731
    r0 = torch.eye(3, dtype=torch.float64) if R0_rect is None else R0_rect
    p = fmt(P2)
    return (f"P0: {p}\nP1: {p}\nP2: {p}\nP3: {p}\nR0_rect: {fmt(r0)}\nTr_velo_to_cam: {fmt(Tr_velo_to_cam)}\n"
            "Tr_imu_to_velo: \n")


def scene_calibration(scene) -> Calibration:
    """The KITTI calibration of a synthetic scene: ``P2 = [K | 0]``, ``R0_rect = I``, ``Tr = sensor_to_camera[:3]``."""
    p2 = torch.zeros(3, 4, dtype=torch.float64)
    p2[:, :3] = scene.intrinsics.to(torch.float64)
    return Calibration(P2=p2, R0_rect=torch.eye(3, dtype=torch.float64),
                       Tr_velo_to_cam=scene.sensor_to_camera.to(torch.float64)[:3].clone())


def write_vod_tree(
    root: PathLike,
    splits: Mapping[str, Sequence],
    sensor: str = "radar_5frames",
    class_names: Sequence[str] = ("Car", "Pedestrian", "Cyclist"),
    other_type: Optional[str] = "bicycle_rack",
    first_id: int = 0,
    image_format: str = "png",
) -> Dict[str, List[str]]:
    """Save synthetic scenes as a View-of-Delft release tree.

    Layout: ``root/sensor/training/velodyne/<id>.bin`` (float32 ``P x 7``: ``x, y, z, RCS, v_r, v_r_comp,
    time``), ``calib/<id>.txt`` (:func:`scene_calibration`), ``image_2/<id>.png`` (8-bit RGB),
    ``label_2/<id>.txt`` (the scene's objects, truncation 0, occlusion 0; and the clutter items as
    ``other_type`` lines, a type the detectors do not learn, unless ``other_type`` is ``None``) and
    ``root/sensor/ImageSets/<split>.txt``. Frame ids are 5-digit numbers, consecutive over the splits in
    the given order.

    Args:
        root: output folder (created).
        splits: ``{split name: scenes}``, e.g. ``{"train": [...], "val": [...]}``.
        sensor: the VoD sensor folder name.
        class_names: names of the scenes' labels.
        other_type: type string of the clutter lines.
        first_id: the first frame id.
        image_format: ``"png"`` (lossless) or ``"jpg"`` (VoD's own files; PIL's default quality).

    Returns:
        ``{split: frame ids}``.
    """
    from PIL import Image

    if image_format not in ("png", "jpg"):
        raise MSSFError(f"image_format: expected 'png' or 'jpg', got {image_format!r}")
    base = Path(root) / sensor
    dirs = {name: base / "training" / name for name in ("velodyne", "calib", "image_2", "label_2")}
    for d in list(dirs.values()) + [base / "ImageSets"]:
        d.mkdir(parents=True, exist_ok=True)
    out: Dict[str, List[str]] = {}
    next_id = int(first_id)
    for split, scenes in splits.items():
        ids = []
        for scene in scenes:
            fid = f"{next_id:05d}"
            next_id += 1
            ids.append(fid)
            np.ascontiguousarray(scene.points.numpy(), dtype="<f4").tofile(dirs["velodyne"] / f"{fid}.bin")
            calib = scene_calibration(scene)
            (dirs["calib"] / f"{fid}.txt").write_text(calibration_text(calib.P2, calib.Tr_velo_to_cam, calib.R0_rect))
            rgb = (scene.image.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()
            Image.fromarray(np.ascontiguousarray(rgb)).save(dirs["image_2"] / f"{fid}.{image_format}")
            lines = kitti_lines(scene.gt_boxes.double(), scene.gt_labels, class_names, calib, scene.image_size,
                                truncated=0.0, occluded=0)
            if other_type is not None and len(scene.clutter_boxes):
                k = len(scene.clutter_boxes)
                lines += kitti_lines(scene.clutter_boxes.double(), torch.zeros(k, dtype=torch.long), class_names,
                                     calib, scene.image_size, truncated=0.0, occluded=0, names=[other_type] * k)
            write_kitti_file(dirs["label_2"] / f"{fid}.txt", lines)
        (base / "ImageSets" / f"{split}.txt").write_text("".join(i + "\n" for i in ids))
        out[split] = ids
    return out

