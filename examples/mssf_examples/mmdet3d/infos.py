"""View-of-Delft / TJ4DRadSet releases -> mmdetection3d 1.x info files (``vod_infos_<split>.pkl``,
``tj4d_infos_<split>.pkl``).

TJ4DRadSet (:func:`create_tj4d_infos`): the KITTI layout ``<root>/training/{velodyne,image_2,calib,label_2}``
with ``<root>/ImageSets``, 8 floats per point (x, y, z, V_r, Range, Power, Alpha, Beta), classes Car,
Pedestrian, Cyclist, Truck (``bbox_label_3d`` 0..3), the frame texts under ``tj4d``; otherwise as below.

Reads the release layout with :class:`~mssf_examples.data.kitti_io.KittiFormatDataset`
(``<root>/<sensor>/training/{velodyne,image_2,calib,label_2}``, the split files in
``<root>/<sensor>/ImageSets`` or ``<root>/lidar/ImageSets``) and writes, per split, the
``{"metainfo", "data_list"}`` dict mmdet3d 1.x datasets load:

* ``lidar_points``: ``lidar_path`` (``<id>.bin``, relative to ``data_prefix['pts']``), ``num_pts_feats`` 7
  (x, y, z, RCS, v_r, v_r_comp, time), ``Tr_velo_to_cam`` (4x4);
* ``images['CAM2']``: ``img_path`` (``<id>.jpg`` as found, relative to ``data_prefix['img']``), ``height``,
  ``width``, ``cam2img`` (``P2`` 4x4), ``lidar2cam`` (``R0_rect @ Tr_velo_to_cam``), ``lidar2img``,
  ``R0_rect``;
* ``instances``: one per label line of a VoD class (Car, Pedestrian, Cyclist -> ``bbox_label_3d`` 0, 1, 2)
  or another type (-1: mmdet3d drops it for training), ``bbox_3d`` in the camera frame as mmdet3d's
  KITTI converter writes it (bottom-face centre, ``(l, h, w)``, ``rotation_y``), ``bbox`` the 2D box,
  ``truncated``, ``occluded``, ``alpha``, ``depth``, ``center_2d``;
* ``vod``: the frame's label and calibration text, for :class:`~mssf_examples.mmdet3d.metric.VoDMetric`,
  which evaluates against them with the kit's rules (every type, ``DontCare`` included).

Command line: ``python -m mssf_examples.mmdet3d infos --root data/view_of_delft --sensor radar_5frames``.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from mssf_blocks.errors import MSSFError

from ..data.kitti_io import TJ4D_CLASSES, TJ4D_RADAR, VOD_CLASSES, VOD_RADAR, KittiFormatDataset

__all__ = ["frame_info", "create_vod_infos", "create_tj4d_infos"]

PathLike = Union[str, Path]


def _4x4(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


def frame_info(dataset: KittiFormatDataset, frame_id: str, with_labels: bool = True,
               classes: Sequence[str] = VOD_CLASSES, text_key: str = "vod") -> Dict:
    """The mmdet3d 1.x info dict of one frame (see the module docstring): labels index ``classes`` (other
    types -1), the label and calibration text under ``text_key``."""
    paths = dataset.paths(frame_id)
    frame = dataset.load(frame_id, with_labels=with_labels)
    calib = frame.calib
    p2 = _4x4(calib.P2.numpy())
    r0 = _4x4(calib.R0_rect.numpy())
    tr = _4x4(calib.Tr_velo_to_cam.numpy())
    lidar2cam = r0 @ tr
    h, w = frame.image_size
    instances: List[Dict] = []
    objs = frame.objects
    if objs is not None:
        for i, name in enumerate(objs.names):
            loc = objs.location[i].numpy()
            hh, ww, ll = objs.dimensions[i].numpy()
            centre = loc - np.array([0.0, hh / 2, 0.0])  # gravity centre (camera y points down)
            uvw = p2[:3] @ np.append(centre, 1.0)
            label = list(classes).index(name) if name in classes else -1
            instances.append({
                "bbox": [float(v) for v in objs.boxes_2d[i].tolist()],
                "bbox_label": label,
                "bbox_3d": [float(loc[0]), float(loc[1]), float(loc[2]), float(ll), float(hh), float(ww),
                            float(objs.rotation_y[i])],
                "bbox_label_3d": label,
                "depth": float(centre[2]),
                "center_2d": [float(uvw[0] / uvw[2]), float(uvw[1] / uvw[2])],
                "num_lidar_pts": -1,
                "difficulty": 0,
                "truncated": float(objs.truncation[i]),
                "occluded": int(objs.occlusion[i]),
                "alpha": float(objs.alpha[i]),
                "score": 0.0,
                "index": i,
                "group_id": i,
            })
    label_text = paths.label.read_text() if with_labels and paths.label is not None else ""
    return {
        "sample_idx": int(frame_id) if str(frame_id).isdigit() else str(frame_id),  # mmengine re-numbers it
        "frame_id": str(frame_id),
        "lidar_points": {"num_pts_feats": int(frame.raw_points.shape[1]), "lidar_path": paths.points.name,
                         "Tr_velo_to_cam": tr},
        "images": {"CAM2": {"img_path": paths.image.name, "height": int(h), "width": int(w), "cam2img": p2,
                            "lidar2cam": lidar2cam, "lidar2img": p2 @ lidar2cam},
                   "R0_rect": r0},
        "instances": instances,
        text_key: {"label_text": label_text, "calib_text": paths.calib.read_text(), "image_size": (int(h), int(w))},
    }


def create_vod_infos(root: PathLike, sensor: str = "radar_5frames", splits: Sequence[str] = ("train", "val"),
                     out_dir: Optional[PathLike] = None, prefix: str = "vod_infos") -> Dict[str, Path]:
    """Write ``<out_dir>/<prefix>_<split>.pkl`` for every split; returns ``{split: path}``.

    Args:
        root: the VoD release root (holding ``radar``, ``radar_5frames``, ``lidar``...).
        sensor: the radar folder (``"radar"``: single scan, ``"radar_5frames"``: the paper's 5-scan input).
        splits: split-file names (``ImageSets/<split>.txt``).
        out_dir: where to write (default ``<root>/<sensor>``, the dataset's ``data_root``).

    Raises:
        FileNotFoundError: a folder, split file or frame file is missing (naming the paths tried).
        MSSFError: point files whose size is not a multiple of 7 floats (VoD radar).
    """
    root = Path(root)
    out = Path(out_dir) if out_dir is not None else root / sensor
    return _write(root, out, splits, prefix, "vod", VOD_CLASSES, sensor,
                  lambda split: KittiFormatDataset(root, VOD_RADAR, sensor=sensor, split=split, load_image=False))


def create_tj4d_infos(root: PathLike, splits: Sequence[str] = ("train", "val"), out_dir: Optional[PathLike] = None,
                      prefix: str = "tj4d_infos") -> Dict[str, Path]:
    """Write ``<out_dir>/<prefix>_<split>.pkl`` for every split of a TJ4DRadSet release; returns ``{split: path}``.

    Args:
        root: the TJ4DRadSet root (holding ``training/`` and ``ImageSets/``).
        splits: split-file names (``ImageSets/<split>.txt``).
        out_dir: where to write (default ``root``, the dataset's ``data_root``).

    Raises:
        FileNotFoundError: a folder, split file or frame file is missing (naming the paths tried).
        MSSFError: point files whose size is not a multiple of 8 floats (TJ4DRadSet radar).
    """
    root = Path(root)
    out = Path(out_dir) if out_dir is not None else root
    return _write(root, out, splits, prefix, "tj4d", TJ4D_CLASSES, None,
                  lambda split: KittiFormatDataset(root, TJ4D_RADAR, sensor=None, split=split,
                                                   class_names=TJ4D_CLASSES, load_image=False))


def _write(root: Path, out: Path, splits: Sequence[str], prefix: str, name: str, classes: Sequence[str],
           sensor: Optional[str], reader) -> Dict[str, Path]:
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for split in splits:
        ds = reader(split)
        data_list = [frame_info(ds, fid, classes=classes, text_key=name) for fid in ds.frame_ids]
        if not data_list:
            raise MSSFError(f"split {split!r}: no frames listed in its split file under {root / (sensor or '')}")
        infos = {"metainfo": {"categories": {c: i for i, c in enumerate(classes)}, "dataset": name,
                              "info_version": "1.1", "sensor": sensor}, "data_list": data_list}
        path = out / f"{prefix}_{split}.pkl"
        with open(path, "wb") as f:
            pickle.dump(infos, f)
        written[split] = path
    return written
