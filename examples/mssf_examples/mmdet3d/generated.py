"""A View-of-Delft release tree of generated scenes with its mmdet3d info files, and an image-branch checkpoint
shaped like the paper's HTC R-50-FPN, for checks that train a shipped mmdet3d config without the licensed data
or a download (the mmdet3d tests and ``make gpu-check``'s framework stage).

The tree is what the VoD release holds for one radar sensor: ``<root>/radar_5frames/training/{velodyne,
image_2,calib,label_2}`` (7-float radar points, ``.jpg`` images) plus ``ImageSets``, and the
``vod_infos_{train,val}.pkl`` that ``python -m mssf_examples.mmdet3d infos`` writes. Needs pillow (the
``examples`` extra), not mmdet3d; the checkpoint needs mmdet (its ResNet and FPN give the key names).
"""

from __future__ import annotations

from pathlib import Path
from typing import Tuple

SENSOR = "radar_5frames"


def write_generated_vod(root, train: int = 4, val: int = 2, image_size: Tuple[int, int] = (304, 484),
                        seed: int = 7, sensor: str = SENSOR) -> Path:
    """Write ``train`` + ``val`` generated frames under ``root/<sensor>`` and their info files.

    ``image_size`` is (H, W) of the written images; ``sensor`` the radar folder (``radar_5frames``, or ``radar``
    for the single-scan configs: the same 7-float files). Returns the data root (``root/<sensor>``).
    """
    from PIL import Image

    from ..data.kitti_export import write_vod_tree
    from ..scenes.synthetic import SceneConfig, SyntheticDataset
    from .infos import create_vod_infos

    root = Path(root)
    cfg = SceneConfig(image_size=image_size, point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0))
    scenes = {"train": [SyntheticDataset("train", train, cfg, seed=seed)[i] for i in range(train)],
              "val": [SyntheticDataset("val", val, cfg, seed=seed)[i] for i in range(val)]}
    write_vod_tree(root, scenes, sensor=sensor)
    for png in (root / sensor / "training" / "image_2").glob("*.png"):  # the release's images are jpg
        Image.open(png).convert("RGB").save(png.with_suffix(".jpg"), quality=95)
        png.unlink()
    create_vod_infos(root, sensor, ("train", "val"))
    return root / sensor


def write_generated_image_checkpoint(path, seed: int = 3) -> Path:
    """An mmdet-style checkpoint shaped like the paper's HTC R-50-FPN: ``{'meta', 'state_dict'}`` with
    ``backbone.*`` (ResNet-50), ``neck.*`` (FPN, 4 levels of 256) and a few of HTC's head keys, every value
    drawn from ``seed`` (running variances positive): what ``train --image-checkpoint`` and the image branch's
    ``init_cfg`` read, where the real file cannot be downloaded. Returns ``path``."""
    import torch
    from mmdet.models.backbones import ResNet
    from mmdet.models.necks import FPN

    g = torch.Generator().manual_seed(seed)
    parts = {"backbone.": ResNet(depth=50).state_dict(),
             "neck.": FPN(in_channels=[256, 512, 1024, 2048], out_channels=256, num_outs=4).state_dict(),
             "rpn_head.": {"rpn_conv.weight": torch.zeros(256, 256, 3, 3), "rpn_cls.weight": torch.zeros(3, 256, 1, 1)},
             "roi_head.": {"bbox_head.0.fc_cls.weight": torch.zeros(11, 1024)}}
    state = {}
    for prefix, sd in parts.items():
        for k, v in sd.items():
            if v.is_floating_point():
                v = torch.rand(v.shape, generator=g) + 0.5 if k.endswith("running_var") else \
                    torch.randn(v.shape, generator=g) * 0.02
            state[prefix + k] = v
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"meta": {"mmdet_version": "2.x", "CLASSES": ("car", "truck")}, "state_dict": state}, path)
    return path
