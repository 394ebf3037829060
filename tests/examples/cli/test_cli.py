"""The train/eval CLI (``python -m mssf_examples``) end to end on a tiny VoD-layout tree the test writes.

The tree holds generated scenes (``generated_tree.py``: :mod:`mssf_examples.scenes.synthetic` saved with
:func:`mssf_examples.data.kitti_export.write_vod_tree`); no licensed frames are used. That the tree and the
prediction files read back as what was written: ``test_kitti_export_tree.py``.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.evaluation.metrics import evaluate  # noqa: E402
from mssf_examples.data.kitti_io import VOD_CLASSES, VOD_RADAR, KittiFormatDataset, parse_labels, read_labels  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from generated_tree import SIZE, write_generated_tree  # noqa: E402

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_generated_tree(tmp_path_factory.mktemp("vod"))


# ---------------------------------------------------------------------------------------------------
# scale_batch: the images and lidar2img together
# ---------------------------------------------------------------------------------------------------
def test_scale_batch_maps_pixels_with_the_image(tree):
    """A 2x2 bright block at pixels (2i..2i+1, 2j..2j+1) lands on pixel (i, j) of the half-size image,
    and the scaled lidar2img projects the block centre's 3D point there."""
    from mssf_examples.data.batch import RadarCameraBatch

    h, w = 32, 48
    img = torch.zeros(1, 1, 3, h, w)
    bi, bj = 7, 10  # half-size pixel (row, col)
    img[..., 2 * bi:2 * bi + 2, 2 * bj:2 * bj + 2] = 1.0
    k = torch.tensor([[40.0, 0, 23.5], [0, 40.0, 15.5], [0, 0, 1]], dtype=torch.float64)
    l2i = torch.cat([k, torch.zeros(3, 1, dtype=torch.float64)], 1)
    u, v, d = 2 * bj + 0.5, 2 * bi + 0.5, 5.0  # the block centre in full-size pixels, at depth 5
    p = torch.linalg.solve(k, torch.tensor([u * d, v * d, d], dtype=torch.float64))
    batch = RadarCameraBatch(points=[torch.zeros(1, 3)], lidar2img=l2i.float()[None, None], images=img)
    out = cli.scale_batch(batch, 0.5)
    assert out.image_size == (16, 24)
    flat = out.images[0, 0, 0]
    assert divmod(int(flat.argmax()), 24) == (bi, bj)
    q = out.lidar2img[0, 0].double() @ torch.cat([p, torch.ones(1, dtype=torch.float64)])
    torch.testing.assert_close(q[:2] / q[2], torch.tensor([bj, bi], dtype=torch.float64), rtol=0, atol=1e-4)


# ---------------------------------------------------------------------------------------------------
# end to end: train 3 steps, eval, files; TJ4DRadSet; and the documented module invocation
# ---------------------------------------------------------------------------------------------------
def _train_args(root, out, *extra):
    return ["train", "--dataset", "vod", "--data-root", str(root), "--preset", "tiny", "--steps", "3",
            "--batch-size", "2", "--threads", "1", "--no-progress", "--out", str(out), *extra]


@pytest.fixture(scope="module")
def trained(tree, tmp_path_factory):
    root, ids, scenes = tree
    out = tmp_path_factory.mktemp("run")
    assert cli.main(_train_args(root, out, "--fusion-blocks", "1")) == 0
    return out


def test_train_writes_checkpoint_and_config(trained):
    assert (trained / "checkpoint.pt").is_file()
    cfg = json.loads((trained / "config.json").read_text())
    assert cfg["dataset"] == "vod" and cfg["sensor"] == "radar_5frames" and cfg["steps"] == 3
    assert cfg["preset"]["image_size"] == list(SIZE)
    assert cfg["preset"]["class_names"] == list(VOD_CLASSES)
    assert math.isfinite(cfg["final_loss"]["loss"])


def test_train_is_deterministic(tree, trained, tmp_path):
    root, _, _ = tree
    assert cli.main(_train_args(root, tmp_path, "--fusion-blocks", "1")) == 0
    a = json.loads((trained / "train_log.json").read_text())
    b = json.loads((tmp_path / "train_log.json").read_text())
    assert a == b


def test_eval_writes_one_prediction_file_per_frame_and_metrics(tree, trained, tmp_path, capsys):
    root, ids, scenes = tree
    out = tmp_path / "eval"
    assert cli.main(["eval", "--checkpoint", str(trained / "checkpoint.pt"), "--data-root", str(root), "--split", "val",
                     "--score-threshold", "0", "--threads", "1", "--no-progress", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Entire annotated area" in printed and "Driving corridor" in printed
    files = sorted(p.stem for p in (out / "predictions").glob("*.txt"))
    assert files == ids["val"]
    m = json.loads((out / "metrics.json").read_text())
    assert set(m["results"]) == {"entire_area", "driving_corridor"}
    assert m["num_frames"] == 2 and m["num_gt"] == sum(len(s.gt_labels) for s in scenes["val"])
    # Independent re-evaluation from the written files (what the official kit reads): parse, evaluate.
    preds, gts = [], []
    ds = KittiFormatDataset(root, VOD_RADAR, sensor="radar_5frames", split="val")
    total = 0
    for frame in ds:
        obj = parse_labels((out / "predictions" / f"{frame.frame_id}.txt").read_text())
        total += len(obj)
        assert obj.score is not None or len(obj) == 0
        preds.append(obj)
        gts.append(read_labels(root / "radar_5frames" / "training" / "label_2" / f"{frame.frame_id}.txt"))
    assert total == m["num_detections"] > 0  # score threshold 0 keeps up to 100 per frame
    assert m["protocol"] == "vod"
    again = evaluate(preds, gts, VOD_CLASSES, protocol="vod")
    for region in again:
        for cls, vals in again[region].items():
            for key, v in vals.items():
                ref = m["results"][region][cls][key]
                if isinstance(v, float) and math.isnan(v):
                    assert ref is None
                else:
                    assert abs(v - ref) < 1e-6, (region, cls, key, v, ref)


def test_train_with_val_split_and_unlabelled_split(tree, tmp_path):
    root, ids, _ = tree
    assert cli.main(_train_args(root, tmp_path, "--fusion-blocks", "0", "--detector", "centerpoint",
                                "--val-split", "val")) == 0
    assert sorted(p.stem for p in (tmp_path / "eval_val" / "predictions").glob("*.txt")) == ids["val"]
    assert (tmp_path / "eval_val" / "metrics.json").is_file()
    # a split without labels (like VoD's test split): prediction files only, no metrics
    unl = tmp_path / "unlabelled"
    sensor = unl / "radar_5frames"
    (sensor / "ImageSets").mkdir(parents=True)
    src = root / "radar_5frames" / "training"
    for sub in ("velodyne", "calib", "image_2"):
        (sensor / "testing" / sub).mkdir(parents=True)
        for f in (src / sub).glob("0000[45].*"):
            (sensor / "testing" / sub / f.name).write_bytes(f.read_bytes())
    (sensor / "training" / "velodyne").mkdir(parents=True)
    (sensor / "ImageSets" / "test.txt").write_text("00004\n00005\n")
    out = tmp_path / "test_eval"
    assert cli.main(["eval", "--checkpoint", str(tmp_path / "checkpoint.pt"), "--data-root", str(unl), "--split", "test",
                     "--threads", "1", "--no-progress", "--out", str(out)]) == 0
    assert sorted(p.stem for p in (out / "predictions").glob("*.txt")) == ["00004", "00005"]
    assert not (out / "metrics.json").exists()


def test_module_help_from_repo_root():
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(["examples", os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    r = subprocess.run([sys.executable, "-m", "mssf_examples", "--help"], cwd=REPO, env=env,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "train" in r.stdout and "eval" in r.stdout


def test_tj4d_layout_train_and_eval(tree, tmp_path):
    """TJ4DRadSet: KITTI layout (root/training, root/ImageSets), 8 stored channels, 4 classes."""
    root, ids, scenes = tree
    src = root / "radar_5frames" / "training"
    tj = tmp_path / "tj4d"
    for sub in ("calib", "image_2", "label_2"):
        (tj / "training" / sub).mkdir(parents=True)
        for f in (src / sub).iterdir():
            (tj / "training" / sub / f.name).write_bytes(f.read_bytes())
    (tj / "training" / "velodyne").mkdir()
    for f in (src / "velodyne").iterdir():
        p = np.fromfile(f, dtype="<f4").reshape(-1, 7)
        rng = np.linalg.norm(p[:, :3], axis=1)
        # x, y, z, V_r, Range, Power, Alpha, Beta
        cols = [p[:, 0], p[:, 1], p[:, 2], p[:, 4], rng, p[:, 3], np.arctan2(p[:, 1], p[:, 0]), np.zeros(len(p))]
        np.stack(cols, 1).astype("<f4").tofile(tj / "training" / "velodyne" / f.name)
    (tj / "ImageSets").mkdir()
    for split in ("train", "val"):
        (tj / "ImageSets" / f"{split}.txt").write_text("\n".join(ids[split]) + "\n")
    out = tmp_path / "run"
    assert cli.main(["train", "--dataset", "tj4d", "--data-root", str(tj), "--preset", "tiny", "--steps", "2",
                     "--batch-size", "2", "--threads", "1", "--no-progress", "--detector", "second",
                     "--fusion-blocks", "1", "--out", str(out)]) == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["sensor"] is None and cfg["preset"]["class_names"] == ["Car", "Pedestrian", "Cyclist", "Truck"]
    assert cfg["preset"]["point_features"] == ["x", "y", "z", "v_rc", "Power"]
    assert cli.main(["eval", "--checkpoint", str(out / "checkpoint.pt"), "--split", "val", "--score-threshold", "0",
                     "--threads", "1", "--no-progress"]) == 0
    m = json.loads((out / "eval_val" / "metrics.json").read_text())
    assert m["protocol"] == "tj4d" and set(m["results"]) == {"range_0_50", "range_0_70", "range_all"}
    assert set(m["results"]["range_all"]) == {"Car", "Pedestrian", "Cyclist", "Truck", "mAP"}
    assert m["results"]["range_all"]["Truck"]["AP3D_R40"] is None  # no truck in the scenes: undefined AP
    assert sorted(p.stem for p in (out / "eval_val" / "predictions").glob("*.txt")) == ids["val"]


# ---------------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------------
def _error(argv, capsys) -> str:
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


def test_missing_data_root_names_the_path(tmp_path, capsys):
    missing = tmp_path / "no_such_dataset"
    err = _error(["train", "--dataset", "vod", "--data-root", str(missing), "--out", str(tmp_path / "o")], capsys)
    assert "--data-root" in err and str(missing) in err


def test_wrong_layout_names_what_was_tried(tmp_path, capsys):
    err = _error(["train", "--dataset", "vod", "--data-root", str(tmp_path), "--out", str(tmp_path / "o")], capsys)
    assert str(tmp_path / "radar_5frames" / "training" / "velodyne") in err


def test_unknown_dataset_is_an_argparse_error(tmp_path, capsys):
    err = _error(["train", "--dataset", "kitti", "--data-root", str(tmp_path), "--out", str(tmp_path)], capsys)
    assert "--dataset" in err and "invalid choice" in err and "'kitti'" in err


@pytest.mark.parametrize("flag,value", [("--steps", "0"), ("--lr", "-1"), ("--batch-size", "x"), ("--fusion-blocks", "-1")])
def test_bad_values_are_argparse_errors(tree, tmp_path, capsys, flag, value):
    root, _, _ = tree
    argv = ["train", "--dataset", "vod", "--data-root", str(root), "--out", str(tmp_path), flag, value]
    err = _error(argv, capsys)
    assert flag in err and value in err


def test_batch_larger_than_split_and_missing_checkpoint(tree, tmp_path, capsys):
    root, _, _ = tree
    err = _error(["train", "--dataset", "vod", "--data-root", str(root), "--batch-size", "5", "--out", str(tmp_path)],
                 capsys)
    assert "--batch-size" in err and "5" in err and "4" in err
    missing = tmp_path / "nope.pt"
    err = _error(["eval", "--checkpoint", str(missing), "--data-root", str(root)], capsys)
    assert "--checkpoint" in err and str(missing) in err


def test_foreign_checkpoint_is_rejected(tree, tmp_path, capsys):
    root, _, _ = tree
    path = tmp_path / "demo.pt"
    torch.save({"models": {}, "config": {}}, path)  # e.g. a train_demo.py checkpoint
    err = _error(["eval", "--checkpoint", str(path), "--data-root", str(root)], capsys)
    assert "--checkpoint" in err and str(path) in err and "mssf-examples-detector/1" in err


# ---------------------------------------------------------------------------------------------------
# training batches: GT boxes outside the grid
# ---------------------------------------------------------------------------------------------------
def test_training_batches_drop_gt_outside_the_grid(tree):
    from mssf_examples.models.presets import VOD

    root, _, _ = tree
    ds = KittiFormatDataset(root, VOD_RADAR, sensor="radar_5frames", split="train")
    frame = ds[0]
    n = len(frame.gt_boxes)
    far = torch.tensor([[60.0, 0.0, -1.0, 4.0, 1.8, 1.5, 0.0], [10.0, -25.6, -1.0, 0.6, 0.6, 1.7, 0.0],
                        [10.0, 25.6, -1.0, 0.6, 0.6, 1.7, 0.0]], dtype=torch.float64)
    frame.boxes = torch.cat([frame.boxes, far])
    frame.labels = torch.cat([frame.labels, torch.tensor([0, 1, 1])])
    kept = cli._Collate(1.0, VOD.point_cloud_range)([frame])
    # x = 60 is beyond 51.2; y = -25.6 is on the closed lower edge (kept), y = 25.6 on the open upper edge
    assert len(kept.gt_boxes[0]) == n + 1
    torch.testing.assert_close(kept.gt_boxes[0][-1].double(), far[1])
    assert len(cli._Collate(1.0)([frame]).gt_boxes[0]) == n + 3
