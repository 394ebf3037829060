"""A View-of-Delft release tree of generated scenes with its mmdet3d info files, for checks that train a
shipped mmdet3d config without the licensed data (the mmdet3d tests and ``make gpu-check``'s framework stage).

The tree is what the VoD release holds for one radar sensor: ``<root>/radar_5frames/training/{velodyne,
image_2,calib,label_2}`` (7-float radar points, ``.jpg`` images) plus ``ImageSets``, and the
``vod_infos_{train,val}.pkl`` that ``python -m mssf_examples.mmdet3d infos`` writes. Needs pillow (the
``examples`` extra), not mmdet3d.
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

SENSOR = "radar_5frames"


def write_generated_vod(root, train: int = 4, val: int = 2, image_size: Tuple[int, int] = (304, 484),
                        seed: int = 7) -> Path:
    """Write ``train`` + ``val`` generated frames under ``root/radar_5frames`` and their info files.

    ``image_size`` is (H, W) of the written images. Returns the data root (``root/radar_5frames``).
    """
    from PIL import Image

    from ..kitti_export import write_vod_tree
    from ..scenes import SceneConfig, SyntheticDataset
    from .infos import create_vod_infos

    root = Path(root)
    cfg = SceneConfig(image_size=image_size, point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0))
    scenes = {"train": [SyntheticDataset("train", train, cfg, seed=seed)[i] for i in range(train)],
              "val": [SyntheticDataset("val", val, cfg, seed=seed)[i] for i in range(val)]}
    write_vod_tree(root, scenes, sensor=SENSOR)
    for png in (root / SENSOR / "training" / "image_2").glob("*.png"):  # the release's images are jpg
        Image.open(png).convert("RGB").save(png.with_suffix(".jpg"), quality=95)
        png.unlink()
    create_vod_infos(root, SENSOR, ("train", "val"))
    return root / SENSOR
