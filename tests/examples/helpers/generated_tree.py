"""The tiny View-of-Delft tree of generated scenes that ``test_cli.py`` and ``test_kitti_export_tree.py`` run on.

The scenes come from :mod:`mssf_examples.scenes.synthetic` and are saved with
:func:`mssf_examples.data.kitti_export.write_vod_tree`; no licensed frames are used.
"""

from __future__ import annotations

from mssf_examples.data.kitti_export import write_vod_tree
from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset

SIZE = (64, 104)


def write_generated_tree(root):
    """Four train and two val scenes (``SIZE`` images) written under ``root``: ``(root, ids, scenes)``, the
    frame ids and the scenes per split."""
    cfg = SceneConfig(image_size=SIZE)
    train = [SyntheticDataset("train", 4, cfg, seed=3)[i] for i in range(4)]
    val = [SyntheticDataset("val", 2, cfg, seed=3)[i] for i in range(2)]
    ids = write_vod_tree(root, {"train": train, "val": val})
    return root, ids, {"train": train, "val": val}
