"""A View-of-Delft release tree of generated scenes (``radar_5frames``, ``.jpg`` images) and its mmdet3d
info files, for the mmdet3d training tests. No licensed frames are used."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

CONFIGS = Path(__file__).resolve().parents[2] / "examples" / "configs" / "mmdet3d"


def require_mmdet3d():
    """Skip without mmdet3d and mmcv's compiled ops; under ``CI=true`` fail instead (the Makefile installs them)."""
    try:
        import mmcv._ext  # noqa: F401
        import mmdet3d.models  # noqa: F401
        import spconv  # noqa: F401
    except ImportError as exc:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"CI=true but mmdet3d / mmcv's compiled ops / spconv do not import ({exc}); "
                        "make test installs ../shared/wheels/mmcv-2.1.0-*.whl", pytrace=False)
        pytest.skip(f"mmdet3d with mmcv's compiled ops not installed ({exc})")


def write_tree(root: Path, train: int = 4, val: int = 2, image_size=(304, 484), seed: int = 7,
               sensor: str = "radar_5frames"):
    """``root/<sensor>`` with ``train`` + ``val`` generated frames (jpg) and ``vod_infos_{train,val}.pkl``.
    Returns the data root (``root/<sensor>``)."""
    from mssf_examples.mmdet3d.generated import write_generated_vod

    return write_generated_vod(root, train, val, image_size, seed, sensor=sensor)


def write_tj4d_tree(root: Path, train: int = 2, val: int = 2, image_size=(304, 484), seed: int = 11,
                    mmdet3d_infos: bool = True):
    """``root`` as a TJ4DRadSet release (``training/{velodyne,image_2,calib,label_2}``, ``ImageSets``) of
    generated scenes: the points stored as TJ4DRadSet's 8 floats (x, y, z, V_r, Range, Power, Alpha, Beta), the
    first car of every frame labelled ``Truck`` (the fourth class), and (``mmdet3d_infos``) mmdet3d's
    ``tj4d_infos_{train,val}.pkl``. Returns ``root`` (the data root)."""
    import shutil

    import numpy as np

    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset

    cfg = SceneConfig(image_size=image_size, point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0))
    scenes = {"train": [SyntheticDataset("train", train, cfg, seed=seed)[i] for i in range(train)],
              "val": [SyntheticDataset("val", val, cfg, seed=seed)[i] for i in range(val)]}
    ids = write_vod_tree(root / "_vod", scenes, sensor="radar")
    src = root / "_vod" / "radar"
    for sub in ("calib", "image_2", "label_2"):
        shutil.copytree(src / "training" / sub, root / "training" / sub)
    (root / "training" / "velodyne").mkdir()
    for f in (src / "training" / "velodyne").iterdir():
        p = np.fromfile(f, dtype="<f4").reshape(-1, 7)
        cols = [p[:, 0], p[:, 1], p[:, 2], p[:, 4], np.linalg.norm(p[:, :3], axis=1), p[:, 3],
                np.arctan2(p[:, 1], p[:, 0]), np.zeros(len(p))]
        np.stack(cols, 1).astype("<f4").tofile(root / "training" / "velodyne" / f.name)
    for f in (root / "training" / "label_2").iterdir():
        f.write_text(f.read_text().replace("Car ", "Truck ", 1))
    shutil.rmtree(root / "_vod")
    (root / "ImageSets").mkdir()
    for split in ("train", "val"):
        (root / "ImageSets" / f"{split}.txt").write_text("\n".join(ids[split]) + "\n")
    if mmdet3d_infos:
        from mssf_examples.mmdet3d.infos import create_tj4d_infos

        create_tj4d_infos(root, ("train", "val"))
    return root


def val_dataset(cfg):
    """The config's validation dataset, built by mmdet3d's registry."""
    from mmdet3d.registry import DATASETS
    from mmengine.registry import init_default_scope

    init_default_scope("mmdet3d")
    return DATASETS.build(cfg.val_dataloader.dataset)


def evaluate_ground_truth(cfg, shift: float = 0.0):
    """The config's ``val_evaluator`` given each validation frame's ground truth as predictions (moved
    ``shift`` metres along x; scores falling from 1 to 0.5): its result dict."""
    import torch
    from mmdet3d.registry import METRICS

    ds = val_dataset(cfg)
    metric = METRICS.build(cfg.val_evaluator)
    metric.dataset_meta = ds.metainfo
    for i in range(len(ds)):
        ann = ds.get_data_info(i)["eval_ann_info"]
        boxes = ann["gt_bboxes_3d"].clone()
        boxes.tensor[:, 0] += shift
        n = len(boxes)
        metric.process({}, [{"sample_idx": i, "pred_instances_3d": {
            "bboxes_3d": boxes, "scores_3d": torch.linspace(1.0, 0.5, n),
            "labels_3d": torch.as_tensor(ann["gt_labels_3d"])}}])
    return metric.evaluate(len(ds))


_FAKE_HTC = []


def fake_htc_checkpoint() -> Path:
    """``mssf_examples.mmdet3d.generated.write_generated_image_checkpoint`` (an HTC-shaped image-branch
    checkpoint of seeded random values) once per process, in a temporary folder removed at exit."""
    if not _FAKE_HTC:
        import atexit
        import shutil
        import tempfile

        folder = Path(tempfile.mkdtemp(prefix="fake_htc_"))
        atexit.register(shutil.rmtree, folder, True)
        from mssf_examples.mmdet3d.generated import write_generated_image_checkpoint

        _FAKE_HTC.append(write_generated_image_checkpoint(folder / "htc_r50_fpn.pth"))
    return _FAKE_HTC[0]


def ci_widths(cfg):
    """The dense 2D part of a SECOND-backbone model (mmdet3d's ``SECOND`` + ``SECONDFPN`` and the box head) at CI
    widths: one layer of 32 channels per block, a 64-channel BEV, a 16-channel shared conv in a centre head. On
    TJ4DRadSet's 200 x 176 BEV map the shipped widths (5 layers of 128 / 256, a 512-channel BEV) took 30-56 s a
    cell on the 2-core CI machine; the sparse encoder, the fusion blocks, the heads' settings and the data path
    stay as shipped. Models without ``pts_backbone`` (MSSF-PP, MSSF-V) are returned unchanged."""
    m = cfg.model
    if m.get("pts_backbone") is None or m.pts_backbone.get("type") != "SECOND":
        return cfg
    m.pts_backbone.update(layer_nums=[1, 1], out_channels=[32, 32])
    m.pts_neck.update(in_channels=[32, 32], out_channels=[32, 32])
    head = m.pts_bbox_head
    if head.type == "Anchor3DHead":
        head.update(in_channels=64, feat_channels=64)
    else:  # the centre heads
        head.update(in_channels=64, share_conv_channel=16)
    return cfg
