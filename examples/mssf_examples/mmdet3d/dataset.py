"""``VoDDataset``: mmdet3d's ``KittiDataset`` with the View-of-Delft classes (Car, Pedestrian, Cyclist);
``TJ4DDataset``: the same with the TJ4DRadSet classes (Car, Pedestrian, Cyclist, Truck), for the info files
of :func:`~mssf_examples.mmdet3d.infos.create_tj4d_infos` (8-float radar read with ``load_dim=8``).

Registered in ``mmdet3d.registry.DATASETS`` by :mod:`mssf_examples.mmdet3d.plugin`. It reads the info
files of :mod:`~mssf_examples.mmdet3d.infos` (7-float radar points, ``.jpg`` images, ``CAM2`` calibration);
everything else is ``KittiDataset``'s. With ``modality['use_camera']`` every frame must carry its
calibration, checked when the dataset is built.
"""

from __future__ import annotations

from mmdet3d.datasets import KittiDataset

from mssf_blocks.errors import MSSFError

from ..data.kitti_io import TJ4D_CLASSES, VOD_CLASSES

__all__ = ["VoDDataset", "TJ4DDataset"]


class VoDDataset(KittiDataset):
    """View-of-Delft in mmdet3d (labels 0, 1, 2 = Car, Pedestrian, Cyclist)."""

    METAINFO = {"classes": VOD_CLASSES, "palette": [(255, 158, 0), (0, 0, 230), (220, 20, 60)]}

    def parse_data_info(self, info: dict) -> dict:
        if self.modality.get("use_camera", False):
            cam = info.get("images", {}).get(self.default_cam_key, {})
            missing = [k for k in ("img_path", "cam2img", "lidar2cam") if k not in cam]
            if missing:
                raise MSSFError(f"ann_file {self.ann_file}: frame {info.get('sample_idx')} has no {missing} under "
                                f"images[{self.default_cam_key!r}]; the camera modality needs the calibration "
                                "(write the infos with python -m mssf_examples.mmdet3d infos)")
        return super().parse_data_info(info)


class TJ4DDataset(VoDDataset):
    """TJ4DRadSet in mmdet3d (labels 0..3 = Car, Pedestrian, Cyclist, Truck)."""

    METAINFO = {"classes": TJ4D_CLASSES,
                "palette": [(255, 158, 0), (0, 0, 230), (220, 20, 60), (112, 128, 144)]}
