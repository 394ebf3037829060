"""TJ4DRadSet in the real mmdetection3d 1.4.0: info files, ``TJ4DDataset``, ``TJ4DMetric`` and the config pair.

On a generated TJ4DRadSet tree (KITTI layout, 8-float points, the four classes; 2 training frames, so
the shipped batch size 4 gives batches of 2), docs/frameworks.md's TJ4DRadSet lines run as printed (the
info files, then the MSSF-PP quick check, ``--iters 2 --image-scale 320 200``, through the entry's
``main``, with a recording hook attached to the runner it builds), and the radar-only twin with only the
data root, the iteration count and the image scale overridden: 2 iterations and validation at the end,
box (and for MSSF semantic) losses present and finite, every fusion parameter with a non-zero gradient,
the TJ4D keys. ``TJ4DMetric`` on the dataset's own ground truth scores what the
project's TJ4D evaluation gives the label files read directly; moved boxes score zero.
"""

from __future__ import annotations

import dataclasses
import math
import shlex
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import (  # noqa: E402
    ci_widths, evaluate_ground_truth, fake_htc_checkpoint, require_mmdet3d, write_tj4d_tree)
from test_mmdet3d_docs import REPO, RUN_TJ4D  # noqa: E402
from test_mmdet3d_train import box_loss_keys, recording_runners, run, small_cfg  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
MSSF, TWIN = "mssf_pointpillars_tj4d.py", "pointpillars_tj4d_radar.py"
#: every TJ4D model and its radar-only twin (MSSF-PP's own run is the docs' quick check, test_docs_lines_run_as_printed)
PAIRS = {MSSF: TWIN, "mssf_second_tj4d.py": "second_tj4d_radar.py",
         "mssf_centerpoint_tj4d.py": "centerpoint_tj4d_radar.py"}
VOXEL_RANGE = [0, -40, -4, 70.4, 40, 2]  # the paper's TJ4D range of the voxel models (SECOND, CenterPoint)
CLASSES = ("Car", "Pedestrian", "Cyclist", "Truck")
REGIONS = ("range_0_50", "range_0_70", "range_all")
KEYS = ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40")


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    require_mmdet3d()
    return write_tj4d_tree(tmp_path_factory.mktemp("tj4d"))


def check_run(rec, fusion, head=None):
    assert len(rec.losses) == 2 and rec.batch_sizes == [2, 2]
    keys = {"loss_cls", "loss_bbox", "loss_dir"} if head is None else box_loss_keys(head)
    for step in rec.losses:
        assert keys <= set(step) and ("loss_seg" in step) == fusion, step
        assert all(math.isfinite(v) for v in step.values()), step
    if fusion:
        assert rec.nonzero and all(rec.nonzero.values()), [n for n, ok in rec.nonzero.items() if not ok]
    else:
        assert not rec.nonzero
    assert [it for it, _ in rec.validations] == [2]
    metrics = rec.validations[0][1]
    assert {f"TJ4D/{r}/{c}/{k}" for r in REGIONS for c in CLASSES + ("mAP",) for k in KEYS} <= set(metrics)


def test_docs_lines_run_as_printed(tmp_path, monkeypatch):
    """docs/frameworks.md's TJ4DRadSet info and quick-check lines, verbatim, in a folder laid out as the docs
    assume (``data/TJ4DRadSet``, ``examples``, ``checkpoints/htc_r50_fpn.pth`` a generated HTC-shaped file)."""
    require_mmdet3d()
    from mssf_examples.mmdet3d.cli import main

    root = write_tj4d_tree(tmp_path / "data" / "TJ4DRadSet")
    for split in ("train", "val"):
        (root / f"tj4d_infos_{split}.pkl").unlink()  # the docs' line writes them
    (tmp_path / "examples").symlink_to(REPO / "examples")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "htc_r50_fpn.pth").symlink_to(fake_htc_checkpoint())  # the page's wget
    monkeypatch.chdir(tmp_path)
    built = recording_runners(monkeypatch)
    for cmd in RUN_TJ4D:
        assert main(shlex.split(cmd)[3:]) == 0, cmd
    assert (root / "tj4d_infos_train.pkl").is_file()
    ((runner, rec),) = built
    cfg = runner.cfg
    assert cfg.model.pts_middle_encoder.point_cloud_range == [0, -39.68, -4, 69.12, 39.68, 2]
    assert cfg.model.pts_middle_encoder.in_channels == 5 and cfg.model.pts_bbox_head.num_classes == 4
    check_run(rec, fusion=True)
    assert (tmp_path / "work_dirs" / "quick_check_tj4d" / "iter_2.pth").is_file()


def test_infos(data_root):
    import pickle

    infos = pickle.loads((data_root / "tj4d_infos_val.pkl").read_bytes())
    assert infos["metainfo"]["categories"] == {c: i for i, c in enumerate(CLASSES)}
    frame = infos["data_list"][0]
    assert frame["lidar_points"]["num_pts_feats"] == 8
    assert (data_root / "training" / "velodyne" / frame["lidar_points"]["lidar_path"]).stat().st_size % 32 == 0
    labels = [i["bbox_label_3d"] for d in infos["data_list"] for i in d["instances"]]
    assert 3 in labels and 0 in labels  # Truck and Car
    text = (data_root / "training" / "label_2" / f"{frame['frame_id']}.txt").read_text()
    assert frame["tj4d"]["label_text"] == text and "vod" not in frame


@pytest.mark.parametrize("name", sorted(set(PAIRS) - {MSSF}) + sorted(PAIRS.values()))
def test_config_trains_and_evaluates(name, data_root, tmp_path):
    cfg = ci_widths(small_cfg(name, data_root, tmp_path))  # SECOND / CenterPoint: the 2D part at CI widths
    head = cfg.model.pts_bbox_head
    assert cfg.model.pts_middle_encoder.in_channels == 5
    if head.type == "Anchor3DHead":
        assert head.num_classes == 4
    else:
        assert [c for t in head.tasks for c in t.class_names] == list(CLASSES)
    if "pointpillars" not in name:  # the voxel models' range, in the data pipeline and in the grid
        assert cfg.model.pts_middle_encoder.point_cloud_range == VOXEL_RANGE
        ranges = [s.point_cloud_range for d in ("train_dataloader", "val_dataloader") for s in cfg[d].dataset.pipeline
                  if "point_cloud_range" in s]
        assert len(ranges) == 3 and all(r == VOXEL_RANGE for r in ranges)
    _, rec = run(cfg)
    check_run(rec, fusion=name in PAIRS, head=head)


@pytest.mark.parametrize("name", sorted(PAIRS))
def test_fusion_removed_is_the_radar_only_twin(name, data_root, tmp_path):
    cfg, twin = small_cfg(name, data_root, tmp_path), small_cfg(PAIRS[name], data_root, tmp_path)
    cfg.model.img_backbone = None
    cfg.model.img_neck = None
    cfg.model.pts_middle_encoder.update(num_fusion_blocks=0, image_channels=None, seg_hidden=None)
    assert cfg.model == twin.model


def _reference(data_root):
    """The project's TJ4D evaluation of the label files' own lines given back with scores (no info file, no
    mmdet3d box conversion)."""
    from mssf_examples.evaluation.metrics import evaluate
    from mssf_examples.data.kitti_io import read_labels

    preds, gts = [], []
    for fid in (data_root / "ImageSets" / "val.txt").read_text().split():
        objs = read_labels(data_root / "training" / "label_2" / f"{fid}.txt")
        keep = [i for i, n in enumerate(objs.names) if n in CLASSES]
        preds.append(dataclasses.replace(
            objs, names=[objs.names[i] for i in keep], truncation=objs.truncation[keep], occlusion=objs.occlusion[keep],
            alpha=objs.alpha[keep], boxes_2d=objs.boxes_2d[keep], dimensions=objs.dimensions[keep],
            location=objs.location[keep], rotation_y=objs.rotation_y[keep],
            score=torch.linspace(1.0, 0.5, len(keep), dtype=torch.float64)))
        gts.append(objs)
    res = evaluate(preds, gts, CLASSES, protocol="tj4d")
    return {f"TJ4D/{r}/{c}/{k}": v[k] for r, per in res.items() for c, v in per.items() for k in KEYS}


def test_metric_matches_the_label_files(data_root, tmp_path):
    cfg = small_cfg(MSSF, data_root, tmp_path)
    assert cfg.val_evaluator.type == "TJ4DMetric"
    got, ref = evaluate_ground_truth(cfg), _reference(data_root)
    assert set(got) == set(ref)
    for k in ref:
        assert (math.isnan(got[k]) and math.isnan(ref[k])) or got[k] == pytest.approx(ref[k], abs=1e-9), k
    assert ref["TJ4D/range_0_70/Truck/AP3D_R40"] > 0.0 and ref["TJ4D/range_0_70/Car/AP3D_R40"] > 0.0
    assert evaluate_ground_truth(cfg, shift=3.0)["TJ4D/range_0_70/mAP/AP3D_R40"] == 0.0
