"""MSSF for OpenPCDet: the View-of-Delft and TJ4DRadSet datasets, MSSF-SECOND, MSSF-VoxelNeXt, MSSF-CenterPoint,
MSSF-PP and VoxelNeXt-2D (docs/frameworks.md).

``register()`` inserts the classes into OpenPCDet's registries (the ``__all__`` dicts of
``pcdet.datasets``, ``pcdet.models.backbones_3d``, ``pcdet.models.backbones_2d`` and ``pcdet.models.detectors``) for users who do
not edit pcdet's ``__init__.py`` files; ``python -m mssf_examples.openpcdet train.py --cfg_file ...``
registers and then runs one of OpenPCDet's ``tools/`` scripts. Importing this package does not import
OpenPCDet; ``register()`` and the submodules ``vod_dataset`` / ``detectors`` do.
"""

from __future__ import annotations

from typing import Dict

__all__ = ["register", "REGISTERED_NAMES"]

#: registry -> the names :func:`register` adds to it
REGISTERED_NAMES = {
    "pcdet.datasets": ("VoDDataset", "TJ4DDataset"),
    "pcdet.models.backbones_3d": ("MSSFVoxelBackBone8x", "MSSFVoxelResBackBone8x", "MSSFVoxelResBackBone8xVoxelNeXt",
                                  "MSSFVoxelResBackBone8xVoxelNeXt2D"),
    "pcdet.models.backbones_2d": ("MSSFBaseBEVBackbone",),
    "pcdet.models.detectors": ("MSSFSECONDNet", "MSSFVoxelNeXt", "MSSFCenterPoint", "MSSFPointPillar"),
}


def register(pure_torch_box_ops: bool = False) -> Dict[str, tuple]:
    """Add the MSSF classes to OpenPCDet's registries (idempotent); returns :data:`REGISTERED_NAMES`.

    Args:
        pure_torch_box_ops: also replace the CUDA extension's rotated NMS / IoU with the project's
            pure-torch ones (:func:`~mssf_examples.openpcdet.box_ops.use_pure_torch_box_ops`), for
            evaluation on a machine where OpenPCDet's extensions are not built.
    """
    import pcdet.datasets as datasets
    import pcdet.models.backbones_2d as backbones_2d
    import pcdet.models.backbones_3d as backbones_3d
    import pcdet.models.detectors as detectors

    from mssf_blocks.integrations.openpcdet_backbones import OPENPCDET_BACKBONES

    from .bev_backbone import OPENPCDET_BEV_BACKBONES
    from .detectors import MSSF_DETECTORS
    from .scatter_ops import use_pure_torch_scatter
    from .tj4d_dataset import TJ4DDataset
    from .voxelnext2d_backbone import OPENPCDET_PILLAR_BACKBONES
    from .vod_dataset import VoDDataset

    datasets.__all__["VoDDataset"] = VoDDataset
    datasets.__all__["TJ4DDataset"] = TJ4DDataset
    backbones_3d.__all__.update(OPENPCDET_BACKBONES)
    backbones_3d.__all__.update(OPENPCDET_PILLAR_BACKBONES)
    use_pure_torch_scatter()  # VoxelNeXt-2D's DynamicPillarVFESimple2D, where torch_scatter is not installed
    backbones_2d.__all__.update(OPENPCDET_BEV_BACKBONES)
    detectors.__all__.update(MSSF_DETECTORS)
    if pure_torch_box_ops:
        from .box_ops import use_pure_torch_box_ops

        use_pure_torch_box_ops()
    return REGISTERED_NAMES
