"""Tests for ``mssf_examples.data.kitti_io.KittiFormatDataset`` on tiny generated trees: the VoD (``radar_5frames``,
splits, ``testing/``) and TJ4DRadSet layouts, ``frames_to_batch``, and the clear errors for missing files and
malformed calibration / label text. References: the written points and calibration text split by hand.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from mssf_blocks.errors import MSSFError
from mssf_examples.data.kitti_io import (
    TJ4D_CLASSES,
    TJ4D_RADAR,
    VOD_RADAR,
    KittiFormatDataset,
    PointFormat,
    frames_to_batch,
    parse_calibration,
    parse_labels,
    read_points,
)

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from kitti_references import PERM, check_round_trips, hand_calib, rot_xyz  # noqa: E402


# ---------------------------------------------------------------------------------------------------
# tiny synthetic trees
# ---------------------------------------------------------------------------------------------------
def _calib_text(g) -> str:
    p2 = [700 + g.uniform(), 0, 600, 40 * g.uniform(), 0, 700, 180, 0.1, 0, 0, 1, 0.003]
    r0 = rot_xyz(*g.uniform(-0.01, 0.01, 3)).ravel().tolist()
    tr = np.concatenate([PERM @ rot_xyz(*g.uniform(-0.1, 0.1, 3)), g.uniform(-1, 1, (3, 1))], axis=1)
    f = lambda v: " ".join(f"{x:.12e}" for x in v)  # noqa: E731
    return f"P0: {f(p2)}\nP2: {f(p2)}\nR0_rect: {f(r0)}\nTr_velo_to_cam: {f(tr.ravel())}\nTr_imu_to_velo: \n"


def _label_text(g, names, score: bool) -> str:
    lines = []
    for name in names:
        vals = [g.uniform(0, 1), g.integers(0, 3), g.uniform(-3, 3), 10, 20, 50, 60,
                *g.uniform(0.5, 3, 3), *g.uniform([-5, 0, 5], [5, 2, 30]), g.uniform(-3, 3)]
        lines.append(name + " " + " ".join(str(v) for v in vals) + (" 1" if score else ""))
    return "\n".join(lines) + "\n"


def _write_frame(d: Path, fid: str, channels: int, g, names, with_label=True, score=False):
    from PIL import Image

    for sub in ("velodyne", "calib", "image_2", "label_2"):
        (d / sub).mkdir(parents=True, exist_ok=True)
    pts = g.normal(size=(int(g.integers(3, 20)), channels)).astype("<f4")
    pts.tofile(d / "velodyne" / f"{fid}.bin")
    (d / "calib" / f"{fid}.txt").write_text(_calib_text(g))
    Image.fromarray(g.integers(0, 255, (6, 8, 3), dtype=np.uint8)).save(d / "image_2" / f"{fid}.png")
    if with_label:
        (d / "label_2" / f"{fid}.txt").write_text(_label_text(g, names, score))
    return pts


def test_vod_5frames_layout_and_splits(tmp_path):
    g = np.random.default_rng(0)
    base = tmp_path / "vod" / "radar_5frames"
    written = {}
    for fid in ("00001", "00002", "00003", "00004"):
        written[fid] = _write_frame(base / "training", fid, 7, g, ["Car", "Cyclist", "DontCare", "rider"], score=True)
    written["09000"] = _write_frame(base / "testing", "09000", 7, g, [], with_label=False)
    sets = base / "ImageSets"
    sets.mkdir()
    (sets / "train.txt").write_text("00001\n00003\n")
    (sets / "val.txt").write_text("00002\n00004\n")
    (sets / "test.txt").write_text("09000\n")

    ds = KittiFormatDataset(tmp_path / "vod", VOD_RADAR, sensor="radar_5frames")
    assert ds.layout == "nested" and ds.frame_ids == ["00001", "00002", "00003", "00004"]
    train = KittiFormatDataset(tmp_path / "vod", VOD_RADAR, sensor="radar_5frames", split="train")
    assert train.frame_ids == ["00001", "00003"] and len(train) == 2
    val = KittiFormatDataset(tmp_path / "vod", VOD_RADAR, sensor="radar_5frames", split="val")
    assert val.frame_ids == ["00002", "00004"]
    frame = val[1]
    assert frame.frame_id == "00004"
    np.testing.assert_array_equal(frame.points.numpy(), written["00004"])
    assert frame.image.shape == (3, 6, 8) and frame.image_size == (6, 8)
    assert frame.labels.tolist() == [0, 2, -1, -1]
    assert frame.objects.score.tolist() == [1.0] * 4
    p2, r0, tr = hand_calib(base / "training/calib/00004.txt")
    np.testing.assert_allclose(frame.lidar2img.numpy(), p2 @ r0 @ tr, rtol=1e-14, atol=1e-12)
    check_round_trips(frame.calib, seed=5)

    batch = frames_to_batch([train[0], train[1]])
    assert batch.batch_size == 2 and tuple(batch.images.shape) == (2, 1, 3, 6, 8)
    np.testing.assert_array_equal(batch.points[1].numpy(), written["00003"])
    assert batch.gt_labels[0].tolist() == [0, 2]
    np.testing.assert_allclose(batch.images[0, 0].numpy() * 255, train[0].image.numpy(), atol=1e-4)
    np.testing.assert_allclose(batch.lidar2img[1, 0].numpy(), train[1].lidar2img.numpy(), rtol=1e-6)

    test = KittiFormatDataset(tmp_path / "vod", VOD_RADAR, sensor="radar_5frames", split="test")
    assert test.frame_ids == ["09000"]
    assert test.data_dir == base / "testing"
    tframe = test.load("09000", with_labels=False)
    assert tframe.boxes.shape == (0, 7) and tframe.objects is None
    with pytest.raises(FileNotFoundError, match="label file not found"):
        test.load("09000")


def test_tj4d_layout_eight_channels(tmp_path):
    g = np.random.default_rng(1)
    pts = _write_frame(tmp_path / "training", "000010", 8, g, ["Truck", "Pedestrian"])
    ds = KittiFormatDataset(tmp_path, TJ4D_RADAR, sensor=None, class_names=TJ4D_CLASSES)
    assert ds.layout == "nested"
    frame = ds.load("000010")
    np.testing.assert_array_equal(frame.raw_points.numpy(), pts)
    # x, y, z, V_r (standing in for v_rc), Power
    np.testing.assert_array_equal(frame.points.numpy(), pts[:, [0, 1, 2, 3, 5]])
    assert frame.labels.tolist() == [3, 1]
    assert frame.objects.score is None
    # the same file read as VoD radar (7 channels) is a clear error unless the sizes happen to divide
    if pts.size % 7:
        with pytest.raises(MSSFError, match="multiple of 7"):
            read_points(tmp_path / "training/velodyne/000010.bin", VOD_RADAR)


def test_missing_files_raise_clear_errors(tmp_path):
    g = np.random.default_rng(2)
    with pytest.raises(FileNotFoundError, match="dataset root not found"):
        KittiFormatDataset(tmp_path / "nope")
    with pytest.raises(FileNotFoundError, match="no point-cloud folder.*radar_3frames"):
        KittiFormatDataset(tmp_path, VOD_RADAR, sensor="radar_3frames")
    base = tmp_path / "radar_3frames" / "training"
    _write_frame(base, "00001", 7, g, ["Car"])
    with pytest.raises(FileNotFoundError, match="split file for split='train' not found"):
        KittiFormatDataset(tmp_path, VOD_RADAR, sensor="radar_3frames", split="train")
    (tmp_path / "radar_3frames" / "ImageSets").mkdir()
    (tmp_path / "radar_3frames" / "ImageSets" / "train.txt").write_text("00001\n00002\n")
    with pytest.raises(FileNotFoundError, match="without a point file.*00002"):
        KittiFormatDataset(tmp_path, VOD_RADAR, sensor="radar_3frames", split="train")
    ds = KittiFormatDataset(tmp_path, VOD_RADAR, sensor="radar_3frames")
    (base / "calib" / "00001.txt").unlink()
    with pytest.raises(FileNotFoundError, match="calibration file not found"):
        ds.load("00001")
    with pytest.raises(FileNotFoundError, match="point file not found"):
        ds.load("00077")
    (base / "calib" / "00001.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(MSSFError, match="expected a P2 line"):
        ds.load("00001")
    (base / "calib" / "00001.txt").write_text(_calib_text(g))
    (base / "image_2" / "00001.png").unlink()
    with pytest.raises(FileNotFoundError, match="image not found"):
        ds.load("00001")
    # VoD release: split files only in lidar/ImageSets
    (tmp_path / "lidar" / "ImageSets").mkdir(parents=True)
    (tmp_path / "lidar" / "ImageSets" / "val.txt").write_text("00001\n")
    assert KittiFormatDataset(tmp_path, VOD_RADAR, sensor="radar_3frames", split="val").frame_ids == ["00001"]
    with pytest.raises(MSSFError, match="expected 15 or 16 fields"):
        parse_labels("Car 0 0 1 2 3\n")
    with pytest.raises(MSSFError, match="expected 9 values for R0_rect"):
        parse_calibration("P2: " + " ".join(["1"] * 12) + "\nTr_velo_to_cam: " + " ".join(["1"] * 12)
                          + "\nR0_rect: 1 0 0\n")
    with pytest.raises(MSSFError, match="features"):
        PointFormat("bad", ("x", "y", "z", "a"), ("x", "y", "z", "b"))
    shutil_tree = tmp_path / "radar_3frames"
    import shutil

    shutil.rmtree(shutil_tree / "training" / "calib")
    with pytest.raises(FileNotFoundError, match="no calib/ folder"):
        KittiFormatDataset(tmp_path, VOD_RADAR, sensor="radar_3frames")


def test_calibration_without_r0_is_identity():
    text = "P2: " + " ".join(str(v) for v in range(12)) + "\nTr_velo_to_cam: " + " ".join(str(v) for v in range(12, 24))
    calib = parse_calibration(text)
    np.testing.assert_array_equal(calib.R0_rect.numpy(), np.eye(3))
    p2 = np.arange(12.0).reshape(3, 4)
    tr = np.eye(4)
    tr[:3] = np.arange(12.0, 24.0).reshape(3, 4)
    np.testing.assert_array_equal(calib.lidar2img.numpy(), p2 @ tr)
