"""TJ4DRadSet for OpenPCDet: ``DATASET: TJ4DDataset`` (a ``KittiDataset`` for TJ4DRadSet's release tree).

What differs from View-of-Delft (:mod:`~mssf_examples.openpcdet.vod_dataset`; the shared parts are
:class:`~mssf_examples.openpcdet.kitti_style_dataset.KittiStyleDataset`):

* points: ``velodyne/<id>.bin`` as float32 ``N x 8`` (``x, y, z, V_r, Range, Power, Alpha, Beta``,
  :data:`mssf_examples.data.kitti_io.TJ4D_RADAR`); the shipped config uses ``x, y, z, V_r, Power`` (the
  paper's ``[x, y, z, v_rc, Power]``: the release holds no ego-motion, so ``V_r`` stands in for ``v_rc``,
  as the mmdetection3d configs do). A file whose ``Range`` column is not ``|x, y, z|`` is refused (a VoD
  file of ``8 k`` points has the size of ``7 k`` TJ4DRadSet points);
* images: ``image_2/<id>.png`` (``IMAGE_FILE_EXTENSION``, default ``.png``);
* classes: ``Car``, ``Pedestrian``, ``Cyclist``, ``Truck``;
* infos: ``tj4d_infos_{train,val,trainval}.pkl`` from :func:`create_tj4d_infos`
  (``python -m mssf_examples.openpcdet create_tj4d_infos``);
* ``evaluation()``: the MSSF authors' TJ4DRadSet protocol (:mod:`mssf_examples.evaluation.tj4d`, the one
  mmdetection3d's ``TJ4DMetric`` runs): cumulative range bins 0-50 m, 0-70 m and all, the overall IoU set
  (Car and Truck 0.5, Pedestrian and Cyclist 0.25), R11 and their "R40" (41 slots / 40).

Importing this module imports OpenPCDet (``pcdet``).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from mssf_blocks.errors import MSSFError

from ..data.kitti_io import TJ4D_RADAR
from ..data.point_layout import column_problem
from ..evaluation.metrics import TJ4D_IOU_THRESHOLDS
from ..evaluation.tj4d import TJ4D_REGIONS, evaluate_tj4d
from .kitti_style_dataset import KittiStyleDataset

__all__ = ["TJ4DDataset", "TJ4D_POINT_FEATURES", "create_tj4d_infos", "check_tj4d_points"]

#: the eight float32 columns of every TJ4DRadSet radar ``.bin``
TJ4D_POINT_FEATURES = tuple(TJ4D_RADAR.channels)


def check_tj4d_points(points: np.ndarray, path: Any) -> np.ndarray:
    """Raise :class:`MSSFError` when ``points (N, 8)`` read from ``path`` cannot be TJ4DRadSet radar points
    (their ``range`` column is the norm of ``x, y, z``: :func:`~mssf_examples.data.point_layout.column_problem`)."""
    if points.size == 0:
        return points
    problem, _ = column_problem(points, TJ4D_RADAR)
    if problem:
        raise MSSFError(f"{path}: read as TJ4DRadSet's 8 float32 columns {list(TJ4D_POINT_FEATURES)}: {problem}. "
                        "DATA_PATH must be a TJ4DRadSet release folder (a View-of-Delft file has 7 columns)")
    return points


class TJ4DDataset(KittiStyleDataset):
    """OpenPCDet dataset over a TJ4DRadSet release folder (``DATA_PATH``: e.g. ``../data/TJ4DRadSet`` with
    ``training/{velodyne,calib,image_2,label_2}`` and ``ImageSets/{train,val}.txt``)."""

    DATASET_NAME = "TJ4D"
    POINT_FEATURES = TJ4D_POINT_FEATURES
    DEFAULT_IMAGE_EXTENSION = ".png"
    INFO_PREFIX = "tj4d"
    INFOS_COMMAND = "create_tj4d_infos"
    SENSOR_FOLDERS = ()
    EVALUATE = staticmethod(evaluate_tj4d)
    REGIONS = tuple(TJ4D_REGIONS)
    IOU_THRESHOLDS = TJ4D_IOU_THRESHOLDS

    def check_points(self, points: np.ndarray, path: Any) -> np.ndarray:
        return check_tj4d_points(points, path)


def create_tj4d_infos(dataset_cfg: Mapping, class_names, data_path, save_path, workers: int = 4):
    """Write ``tj4d_infos_{train,val,trainval}.pkl`` into ``save_path`` (OpenPCDet's KITTI info format)."""
    return TJ4DDataset.create_infos(dataset_cfg, class_names, data_path, save_path, workers=workers)
