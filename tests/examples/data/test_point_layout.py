"""Issue 42, item 1: the CLI tells VoD from TJ4DRadSet point files by their values, not their size alone.

A file of ``8 k`` VoD points (``56 k`` floats) is also ``7 k`` rows of TJ4DRadSet's 8 floats; the real VoD
frame 01047 (352 points) is one. The files here are written by hand in each dataset's columns (VoD:
``x, y, z, RCS, v_r, v_r_comp, time``; TJ4DRadSet: ``x, y, z, V_r, Range, Power, Alpha, Beta``, Range the
distance of ``x, y, z``), at sizes that divide into rows of both widths, and the real VoD frames where
``../shared/realdata`` is present. Before the fix every one of them passed as the ``--dataset`` given.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("PIL")

from mssf_examples.data.kitti_io import KITTI_LIDAR, TJ4D_RADAR, VOD_RADAR  # noqa: E402
from mssf_examples.data.point_layout import plausible_layouts, read_layouts  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from cli_refusal import refused_line as _fails  # noqa: E402
from generated_tree import write_generated_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
FORMATS = (VOD_RADAR, TJ4D_RADAR)


def vod_points(n: int, seed: int, scans: int = 5) -> np.ndarray:
    """``(n, 7)`` VoD-like radar points: ahead of the car, RCS in dBsm, radial speeds, scan offsets 0..-4."""
    g = np.random.default_rng(seed)
    r, az, el = g.uniform(2, 50, n), g.uniform(-0.7, 0.7, n), g.uniform(-0.1, 0.15, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    v_r = g.normal(0, 4, n)
    cols = [xyz, g.uniform(-30, 25, (n, 1)), v_r[:, None], (v_r + g.normal(0, 1, n))[:, None],
            -g.integers(0, scans, (n, 1)).astype(np.float64)]
    return np.concatenate(cols, 1).astype("<f4")


def tj4d_points(n: int, seed: int) -> np.ndarray:
    """``(n, 8)`` TJ4DRadSet-like radar points: Range ``= |x, y, z|``, Power, Alpha / Beta in degrees."""
    g = np.random.default_rng(seed)
    r, az, el = g.uniform(3, 70, n), g.uniform(-0.6, 0.6, n), g.uniform(-0.15, 0.2, n)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1).astype("<f4")
    rng = np.linalg.norm(xyz.astype(np.float64), axis=1)
    cols = [xyz, g.normal(0, 5, (n, 1)), rng[:, None], g.uniform(5, 30, (n, 1)), np.degrees(az)[:, None],
            np.degrees(el)[:, None]]
    return np.concatenate(cols, 1).astype("<f4")


def _both_widths(points: np.ndarray) -> np.ndarray:
    assert points.size % 56 == 0, "the size must divide into rows of 7 and of 8"
    return points


# ---------------------------------------------------------------------------------------------------
# the readings
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("rows", [8, 16, 64, 352])
def test_vod_points_of_both_sizes_read_as_vod_only(rows):
    for seed, scans in ((0, 1), (1, 5)):
        data = _both_widths(vod_points(rows, seed, scans))
        readings = read_layouts(data, FORMATS)
        assert all(r.fits for r in readings)
        assert [r.point_format for r in plausible_layouts(readings)] == [VOD_RADAR], [r.describe() for r in readings]
        assert "column 'range' differs from |x, y, z|" in readings[1].describe()


@pytest.mark.parametrize("rows", [7, 14, 56, 308])
def test_tj4d_points_of_both_sizes_read_as_tj4d_only(rows):
    data = _both_widths(tj4d_points(rows, seed=rows))
    readings = read_layouts(data, FORMATS)
    assert [r.point_format for r in plausible_layouts(readings)] == [TJ4D_RADAR], [r.describe() for r in readings]
    assert "column 'time' is not a scan offset" in readings[0].describe()


def test_kitti_lidar_points_read_as_neither_radar_dataset():
    g = np.random.default_rng(3)
    data = np.concatenate([g.uniform(-40, 40, (56, 3)), g.uniform(0, 1, (56, 1))], 1).astype("<f4")
    readings = read_layouts(data, (*FORMATS, KITTI_LIDAR))
    assert [r.point_format for r in plausible_layouts(readings)] == [KITTI_LIDAR]


def test_real_vod_frames_read_as_vod_only(realdata_root):
    for fid in ("00549", "01047"):
        readings = read_layouts(realdata_root / "vod" / "radar" / "velodyne" / f"{fid}.bin", FORMATS)
        assert [r.point_format for r in plausible_layouts(readings)] == [VOD_RADAR], [r.describe() for r in readings]
    # 01047's 352 points are also 308 rows of 8: the size alone would have passed it as TJ4DRadSet
    assert read_layouts(realdata_root / "vod/radar/velodyne/01047.bin", FORMATS)[1].fits


# ---------------------------------------------------------------------------------------------------
# the CLI: one line naming the file, both readings and --dataset (exit status 2, no traceback)
# ---------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root, ids, _ = write_generated_tree(tmp_path_factory.mktemp("vod"))
    return root, ids


def _train(root, out, dataset, *extra):
    return ["train", "--dataset", dataset, "--data-root", str(root), "--preset", "tiny", "--steps", "1",
            "--batch-size", "2", "--threads", "1", "--no-progress", "--workers", "0", "--out", str(out), *extra]




def _rewrite_points(velodyne: Path, make) -> Path:
    """Every point file of ``velodyne`` replaced by ``make(seed)``; returns the first file."""
    files = sorted(velodyne.glob("*.bin"))
    for i, f in enumerate(files):
        make(i).tofile(f)
    return files[0]


def _tj4d_tree(root: Path, dst: Path) -> Path:
    """The generated tree's frames in TJ4DRadSet's layout (``dst/training``, ``dst/ImageSets``)."""
    src = root / "radar_5frames"
    shutil.copytree(src / "training", dst / "training")
    shutil.copytree(src / "ImageSets", dst / "ImageSets")
    return dst


def test_cli_refuses_vod_points_of_both_sizes_as_tj4d(tree, tmp_path, capsys):
    tj = _tj4d_tree(tree[0], tmp_path / "tj")
    first = _rewrite_points(tj / "training" / "velodyne", lambda i: _both_widths(vod_points(64, i)))
    line = _fails(_train(tj, tmp_path / "o", "tj4d"), capsys)
    assert str(first) in line and "--dataset tj4d" in line and "pass --dataset vod" in line
    assert "rows of 7 (vod_radar): plausible" in line and "rows of 8 (tj4d_radar): column 'range'" in line


def test_cli_refuses_tj4d_points_of_both_sizes_as_vod(tree, tmp_path, capsys):
    vod = tmp_path / "vod"
    shutil.copytree(tree[0], vod)
    first = _rewrite_points(vod / "radar_5frames" / "training" / "velodyne",
                            lambda i: _both_widths(tj4d_points(56, i)))
    line = _fails(_train(vod, tmp_path / "o", "vod"), capsys)
    assert str(first) in line and "--dataset vod" in line and "pass --dataset tj4d" in line
    assert "rows of 8 (tj4d_radar): plausible" in line and "rows of 7 (vod_radar): column 'time'" in line


def test_cli_refuses_a_file_of_neither_dataset(tree, tmp_path, capsys):
    """KITTI LiDAR rows (x, y, z, reflectance) in a VoD tree, 224 points: rows of 7 and of 8 by size."""
    vod = tmp_path / "vod"
    shutil.copytree(tree[0], vod)
    g = np.random.default_rng(0)
    lidar = lambda i: np.concatenate([g.uniform(-40, 40, (224, 3)), g.uniform(0, 1, (224, 1))], 1).astype("<f4")  # noqa: E731
    first = _rewrite_points(vod / "radar_5frames" / "training" / "velodyne", lidar)
    line = _fails(_train(vod, tmp_path / "o", "vod"), capsys)
    assert str(first) in line and "reads as no dataset's points" in line and "--dataset vod / tj4d" in line
    assert "rows of 7 (vod_radar): column 'time'" in line and "rows of 8 (tj4d_radar): column 'range'" in line


def test_cli_refuses_a_file_both_datasets_read_alike(tree, tmp_path, capsys):
    """All zeros: a time of 0 and a range of 0 at the origin fit both layouts, with different points."""
    vod = tmp_path / "vod"
    shutil.copytree(tree[0], vod)
    first = _rewrite_points(vod / "radar_5frames" / "training" / "velodyne", lambda i: np.zeros(448, "<f4"))
    line = _fails(_train(vod, tmp_path / "o", "vod"), capsys)
    assert str(first) in line and "more than one dataset's points, as vod and tj4d" in line
    assert "--dataset vod" in line


def test_cli_takes_the_real_vod_frame_of_both_sizes_as_vod_only(realdata_root, tmp_path, capsys):
    """A flat tree holding only the real frame 01047 (352 points = 308 rows of 8)."""
    from mssf_examples.cli.args import DATASETS, build_parser
    from mssf_examples.cli.loading import _open_dataset

    src = realdata_root / "vod"
    root = tmp_path / "vod"
    for sub, ext in (("radar/velodyne", "bin"), ("radar/calib", "txt"), ("image_2", "jpg"), ("label_2", "txt")):
        (root / sub).mkdir(parents=True)
        shutil.copyfile(src / sub / f"01047.{ext}", root / sub / f"01047.{ext}")
    line = _fails(_train(root, tmp_path / "o", "tj4d", "--sensor", "radar", "--split", "all", "--batch-size", "1"), capsys)
    assert "01047.bin" in line and "holds vod's points" in line and "pass --dataset vod" in line
    ds = _open_dataset(build_parser(), root, DATASETS["vod"], "radar", "all")  # no error
    assert ds.frame_ids == ["01047"]


# ---------------------------------------------------------------------------------------------------
# the reader (KittiFormatDataset, read_points): the same mistake outside the CLI
# ---------------------------------------------------------------------------------------------------
def test_read_points_refuses_another_datasets_points_of_both_sizes(tmp_path):
    from mssf_blocks.errors import MSSFError
    from mssf_examples.data.kitti_io import read_points

    vod, tj4d = tmp_path / "vod.bin", tmp_path / "tj4d.bin"
    _both_widths(vod_points(64, 0)).tofile(vod)
    _both_widths(tj4d_points(56, 1)).tofile(tj4d)
    assert read_points(vod, VOD_RADAR).shape == (64, 7) and read_points(tj4d, TJ4D_RADAR).shape == (56, 8)
    with pytest.raises(MSSFError, match=r"vod.bin: point_format tj4d_radar does not fit the values, vod_radar does "
                                        r".*pass point_format=VOD_RADAR"):
        read_points(vod, TJ4D_RADAR)
    with pytest.raises(MSSFError, match=r"tj4d.bin: point_format vod_radar does not fit .*pass point_format=TJ4D_RADAR"):
        read_points(tj4d, VOD_RADAR)
    # values that fit no layout (random numbers, as in test_kitti_layouts.py) are left to the size check
    np.random.default_rng(0).normal(size=(8, 7)).astype("<f4").tofile(vod)
    assert read_points(vod, TJ4D_RADAR).shape == (7, 8)
