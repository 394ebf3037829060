"""View-of-Delft for OpenPCDet: ``DATASET: VoDDataset`` (a ``KittiDataset`` for VoD's release tree; the parts
shared with TJ4DRadSet are :class:`~mssf_examples.openpcdet.kitti_style_dataset.KittiStyleDataset`).

What differs from OpenPCDet's ``KittiDataset`` (which would read a VoD radar ``.bin`` as 4 floats per
point and look for ``image_2/<id>.png``):

* points: ``velodyne/<id>.bin`` as float32 ``N x 7`` (``x, y, z, RCS, v_r, v_r_compensated, time``)
  for ``radar``, ``radar_3frames`` and ``radar_5frames`` alike; ``POINT_FEATURE_ENCODING`` must list
  those seven as ``src_feature_list``;
* images: ``image_2/<id>.jpg`` (``IMAGE_FILE_EXTENSION``, default ``.jpg``);
* calibration and labels: VoD's KITTI-style files (``P2``, ``R0_rect``, ``Tr_velo_to_cam`` = radar to
  camera; the label's 16th column is VoD's, unused), the VoD classes (``Car``, ``Pedestrian``,
  ``Cyclist`` learned; other types such as ``bicycle`` or ``rider`` are kept in the infos and
  dropped from training like any class not in ``CLASS_NAMES``);
* infos: :func:`create_vod_infos` (``python -m mssf_examples.openpcdet create_vod_infos``), no
  ground-truth database (the paper's VoD recipe does not sample ground truth);
* ``evaluation()``: the VoD devkit's protocol rule for rule (:mod:`mssf_examples.evaluation.vod`:
  entire annotated area and driving corridor, IoU 0.5 / 0.25 / 0.25, R11 and R40), not KITTI's.

Importing this module imports OpenPCDet (``pcdet``).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from mssf_blocks.errors import MSSFError

from ..evaluation.metrics import VOD_IOU_THRESHOLDS
from ..evaluation.vod import VOD_REGIONS, evaluate_vod
from .kitti_style_dataset import KittiStyleDataset, annos_to_objects

__all__ = ["VoDDataset", "VOD_POINT_FEATURES", "create_vod_infos", "annos_to_objects", "check_dataset_cfg",
           "check_vod_points"]

#: the seven float32 columns of every VoD radar ``.bin``
VOD_POINT_FEATURES = ("x", "y", "z", "rcs", "v_r", "v_r_comp", "time")


def check_dataset_cfg(dataset_cfg: Mapping) -> None:
    """Raise :class:`MSSFError` naming the key when a VoD dataset config cannot read VoD's points."""
    VoDDataset.check_dataset_cfg(dataset_cfg)


#: largest |time| of a VoD radar point: 0 for the current scan, small negative for the earlier scans of
#: ``radar_3frames`` / ``radar_5frames``; a file of another layout read as 7 columns puts coordinates here
_VOD_MAX_ABS_TIME = 10.0


def check_vod_points(points: np.ndarray, path: Any) -> np.ndarray:
    """Raise :class:`MSSFError` when ``points (N, 7)`` read from ``path`` cannot be VoD radar points.

    The file size alone cannot tell the layouts apart (a file of ``28 k`` float32 divides by 4 and by 7):
    a 4-float file (KITTI / VoD ``lidar``: ``x, y, z, reflectance``) or an 8-float one (TJ4DRadSet) read as
    7 columns rotates its fields through the columns, so VoD's ``time`` column (0 for the current scan,
    small and negative for the earlier ones) holds coordinates and ranges of metres."""
    if points.size == 0:
        return points
    if not np.isfinite(points).all():
        raise MSSFError(f"{path}: non-finite values read as VoD's 7 float32 columns {list(VOD_POINT_FEATURES)}: "
                        "not a VoD radar file (another dtype or layout?)")
    worst = float(np.abs(points[:, 6]).max())
    if worst > _VOD_MAX_ABS_TIME:
        guess = "; ".join(f"{k} columns: {points.size // k} points" for k in (4, 5, 8) if points.size % k == 0)
        raise MSSFError(f"{path}: read as VoD's 7 float32 columns {list(VOD_POINT_FEATURES)}, the 'time' column "
                        f"reaches |{worst:.3g}| (VoD: 0 for the current scan, at most {_VOD_MAX_ABS_TIME:g} in magnitude "
                        f"for earlier ones): the file has another layout or dtype ({guess or 'not a multiple of 4, 5 or 8'} "
                        "float32 columns; float64 doubles the count)."
                        " DATA_PATH must be a VoD radar folder (radar, radar_3frames, radar_5frames), not lidar")
    return points


#: VoD's sensor folders (the release's layout)
_VOD_SENSOR_FOLDERS = ("radar", "radar_3frames", "radar_5frames", "lidar")


class VoDDataset(KittiStyleDataset):
    """OpenPCDet dataset over a VoD sensor folder (``DATA_PATH``: e.g. ``view_of_delft/radar_5frames``
    with ``training/{velodyne,calib,image_2,label_2}`` and ``ImageSets/{train,val,test}.txt``).

    ``require_infos=False`` (used by :func:`create_vod_infos`) accepts a folder without info files; otherwise
    a split that loads no frame is an error that says why (KittiDataset logs "Total samples: 0" and torch's
    sampler fails later)."""

    DATASET_NAME = "VoD"
    POINT_FEATURES = VOD_POINT_FEATURES
    DEFAULT_IMAGE_EXTENSION = ".jpg"
    INFO_PREFIX = "vod"
    INFOS_COMMAND = "create_vod_infos"
    SENSOR_FOLDERS = _VOD_SENSOR_FOLDERS
    EVALUATE = staticmethod(evaluate_vod)
    REGIONS = tuple(VOD_REGIONS)
    IOU_THRESHOLDS = VOD_IOU_THRESHOLDS

    def check_points(self, points: np.ndarray, path: Any) -> np.ndarray:
        return check_vod_points(points, path)


def create_vod_infos(dataset_cfg, class_names, data_path, save_path, workers: int = 4):
    """Write ``vod_infos_{train,val,trainval}.pkl`` (and ``_test`` when ``ImageSets/test.txt`` and
    ``testing/`` exist) into ``save_path``, as OpenPCDet's ``create_kitti_infos`` does for KITTI."""
    return VoDDataset.create_infos(dataset_cfg, class_names, data_path, save_path, workers=workers)
