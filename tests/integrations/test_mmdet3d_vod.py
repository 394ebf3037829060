"""View-of-Delft in the real mmdet3d: ``VoDMetric`` on known answers, a learning signal, and the clear errors.

* ``VoDMetric``: the dataset's own ground truth (camera-frame label lines -> info file -> mmdet3d's
  ``KittiDataset`` conversion to LiDAR boxes) given back as predictions scores exactly what the project's
  VoD evaluation gives the label files' own lines (read directly, no conversion): every AP, both regions;
  the same boxes moved 3 m score zero (the metric can fail).
* overfitting one generated frame with MSSF-PointPillars and with MSSF-CenterPoint lowers the total loss clearly.
* bad input: image-neck levels / channels vs ``image_channels``, fusion without an image branch, no box
  head, a pipeline without images or without ``lidar2img``, infos without calibration, a point dimension
  that differs from ``in_channels`` (build time or first iteration, naming the key).
"""

from __future__ import annotations

import math
import pickle
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import ci_widths, evaluate_ground_truth, require_mmdet3d, val_dataset, write_tree  # noqa: E402
from test_mmdet3d_train import small_cfg  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    require_mmdet3d()
    return write_tree(tmp_path_factory.mktemp("vod"))


def _reference(data_root, split="val"):
    """The project's VoD evaluation of each frame's own label lines given back with scores, read from the
    label_2 files directly (no mmdet3d box conversion, no info file)."""
    import dataclasses

    from mssf_examples.evaluation.metrics import evaluate
    from mssf_examples.data.kitti_io import VOD_CLASSES, read_labels

    ids = (data_root / "ImageSets" / f"{split}.txt").read_text().split()
    preds, gts = [], []
    for fid in ids:
        objs = read_labels(data_root / "training" / "label_2" / f"{fid}.txt")
        keep = [i for i, n in enumerate(objs.names) if n in VOD_CLASSES]
        sub = dataclasses.replace(
            objs, names=[objs.names[i] for i in keep], truncation=objs.truncation[keep], occlusion=objs.occlusion[keep],
            alpha=objs.alpha[keep], boxes_2d=objs.boxes_2d[keep], dimensions=objs.dimensions[keep],
            location=objs.location[keep], rotation_y=objs.rotation_y[keep],
            score=torch.linspace(1.0, 0.5, len(keep), dtype=torch.float64))
        preds.append(sub)
        gts.append(objs)
    res = evaluate(preds, gts, VOD_CLASSES, protocol="vod")
    return {f"VoD/{r}/{c}/{k}": v[k] for r, per in res.items() for c, v in per.items()
            for k in ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40")}


def test_metric_matches_the_label_files(data_root, tmp_path):
    cfg = small_cfg("mssf_pointpillars_vod.py", data_root, tmp_path)
    got = evaluate_ground_truth(cfg)
    ref = _reference(data_root)
    assert set(got) == set(ref)
    defined = [k for k, v in ref.items() if not math.isnan(v)]
    assert any("/Car/" in k for k in defined) and any("driving_corridor" in k for k in defined)
    for k in ref:
        assert (math.isnan(got[k]) and math.isnan(ref[k])) or got[k] == pytest.approx(ref[k], abs=1e-9), k
    # (the kit fills one precision slot per counted object, so a perfect score on a few objects is small)
    assert ref["VoD/entire_area/mAP/AP3D_R40"] > 0.0
    moved = evaluate_ground_truth(cfg, shift=3.0)
    assert moved["VoD/entire_area/mAP/AP3D_R40"] == 0.0


@pytest.mark.parametrize("name", ["mssf_pointpillars_vod.py", "mssf_centerpoint_vod.py"])
def test_overfit_one_frame_lowers_the_loss(name, data_root, tmp_path):
    from test_mmdet3d_train import run

    cfg = ci_widths(small_cfg(name, data_root, tmp_path, iters=10))  # (CenterPoint: the 2D part at CI widths)
    cfg.train_dataloader.dataset.indices = 1  # one frame
    pipe = cfg.train_dataloader.dataset.pipeline  # the same frame every time: no point augmentation
    cfg.train_dataloader.dataset.pipeline = [s for s in pipe if s.type not in ("RandomFlip3D", "GlobalRotScaleTrans")]
    cfg.param_scheduler = []  # constant lr 1e-3 (AdamW)
    _, rec = run(cfg)
    total = [s["loss"] for s in rec.losses]
    assert len(total) == 10 and all(math.isfinite(v) for v in total)
    first, last = sum(total[:3]) / 3, sum(total[-3:]) / 3
    print("overfit losses", [round(v, 3) for v in total])
    assert last < 0.6 * first, total


def _build(model_cfg):
    from mmdet3d.registry import MODELS

    return MODELS.build(model_cfg)


@pytest.mark.parametrize("name", ["mssf_pointpillars_vod.py", "mssf_second_vod.py"])
def test_build_errors(name, data_root, tmp_path):
    from mssf_blocks import MSSFError

    cfg = small_cfg(name, data_root, tmp_path)
    for channels in ([256, 256, 256], [128, 128, 128, 128]):
        bad = cfg.model.deepcopy()
        bad.pts_middle_encoder.image_channels = channels
        with pytest.raises(MSSFError, match="image_channels"):
            _build(bad)
    bad = cfg.model.deepcopy()
    bad.img_backbone = None
    with pytest.raises(MSSFError, match="img_backbone"):
        _build(bad)
    bad = cfg.model.deepcopy()
    bad.pts_bbox_head = None
    with pytest.raises(MSSFError, match="pts_bbox_head"):
        _build(bad)
    if name == "mssf_second_vod.py":
        bad = cfg.model.deepcopy()
        bad.pts_voxel_encoder.num_features = 4
        with pytest.raises(MSSFError, match="num_features"):
            _build(bad)


def _first_iteration_error(cfg, match):
    from mmengine.runner import Runner

    from mssf_blocks import MSSFError

    from mssf_examples.mmdet3d.cli import release_workers

    runner = Runner.from_cfg(cfg)
    try:
        with pytest.raises(MSSFError, match=match):
            runner.train()
    finally:
        release_workers(runner)


def _pipeline(cfg):
    return cfg.train_dataloader.dataset.pipeline


def test_pipeline_without_images(data_root, tmp_path):
    cfg = small_cfg("mssf_pointpillars_vod.py", data_root, tmp_path)
    pipe = [s for s in _pipeline(cfg) if s.type not in ("LoadImageFromFile", "Resize")]
    pipe[-1]["keys"] = ["points", "gt_bboxes_3d", "gt_labels_3d"]
    cfg.train_dataloader.dataset.pipeline = pipe
    _first_iteration_error(cfg, "imgs")


def test_pipeline_without_lidar2img(data_root, tmp_path):
    from mmdet3d.datasets.transforms import Pack3DDetInputs

    cfg = small_cfg("mssf_second_vod.py", data_root, tmp_path)
    default = Pack3DDetInputs(keys=["points"]).meta_keys
    _pipeline(cfg)[-1].meta_keys = [k for k in default if k != "lidar2img"]
    _first_iteration_error(cfg, "lidar2img")


def test_point_dimension_differs_from_in_channels(data_root, tmp_path):
    cfg = small_cfg("mssf_pointpillars_vod.py", data_root, tmp_path)
    _pipeline(cfg)[0].use_dim = 5
    _first_iteration_error(cfg, r"in_channels")


def test_infos_without_calibration(data_root, tmp_path):
    from mssf_blocks import MSSFError

    infos = pickle.loads((data_root / "vod_infos_val.pkl").read_bytes())
    del infos["data_list"][0]["images"]["CAM2"]["cam2img"]
    (data_root / "no_calib.pkl").write_bytes(pickle.dumps(infos))
    cfg = small_cfg("mssf_second_vod.py", data_root, tmp_path)
    cfg.val_dataloader.dataset.ann_file = "no_calib.pkl"
    with pytest.raises(MSSFError, match="cam2img"):
        val_dataset(cfg)
