"""Registers the mmdet3d pieces of the examples: ``MSSFDetector``, ``CenterHeadWithoutVelocity`` and
``MSSFVoxelNeXtHead`` (MODELS), ``VoDDataset`` and ``TJ4DDataset`` (DATASETS), ``VoDMetric`` and ``TJ4DMetric``
(METRICS), and through :mod:`mssf_blocks.integrations.mmdet3d_plugin` the MSSF encoders (MODELS).

Name it in a config's ``custom_imports`` (the shipped configs under ``examples/configs/mmdet3d`` do).
Needs mmdet3d with mmcv's compiled ops.
"""

from __future__ import annotations

from mmdet3d.registry import DATASETS, METRICS, MODELS

from mssf_blocks.integrations import mmdet3d_plugin

from .center_head import CenterHeadWithoutVelocity
from .dataset import TJ4DDataset, VoDDataset
from .detector import MSSFDetector
from .metric import TJ4DMetric, VoDMetric
from .voxelnext_head import MSSFVoxelNeXtHead

__all__ = ["MSSFDetector", "CenterHeadWithoutVelocity", "MSSFVoxelNeXtHead", "VoDDataset", "TJ4DDataset", "VoDMetric",
           "TJ4DMetric"]

if not mmdet3d_plugin.REGISTERED:
    raise ImportError("mssf_blocks.integrations.mmdet3d_plugin did not register (mmdet3d not importable)")
for _registry, _cls in ((MODELS, MSSFDetector), (MODELS, CenterHeadWithoutVelocity), (MODELS, MSSFVoxelNeXtHead),
                        (DATASETS, VoDDataset), (DATASETS, TJ4DDataset), (METRICS, VoDMetric), (METRICS, TJ4DMetric)):
    if _registry.module_dict.get(_cls.__name__) is not _cls:
        _registry.register_module(name=_cls.__name__, module=_cls, force=True)
