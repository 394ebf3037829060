"""VoD data set-ups that gave OpenPCDet no frame or wrong points, through its own ``build_dataloader``.

A generated VoD tree (``radar_5frames`` with its infos, and a ``radar`` copy without infos) under
OpenPCDet's ``data/``. Before: a ``DATA_PATH`` without the info files logged "Total samples for KITTI
dataset: 0" and torch's sampler failed (``num_samples=0``); 4-float points whose size divides by 7 were read
as 7-float VoD points.
"""

from __future__ import annotations

import os
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
from test_openpcdet_vod import CONFIGS, load  # noqa: E402

from mssf_blocks import MSSFError  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
BASE = "../data/vod_checks"  # from tools/


@pytest.fixture(scope="module")
def tools(openpcdet):
    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import generate_scene, scene_seed

    tools = openpcdet / "tools"
    shutil.copytree(CONFIGS / "dataset_configs", tools / "cfgs" / "dataset_configs", dirs_exist_ok=True)
    shutil.copytree(CONFIGS / "vod_models", tools / "cfgs" / "vod_models", dirs_exist_ok=True)
    splits = {s: [generate_scene(scene_seed(5, s, i)) for i in range(2)] for s in ("train", "val")}
    write_vod_tree(openpcdet / "data" / "vod_checks", splits, sensor="radar_5frames", image_format="jpg")
    cwd = os.getcwd()
    os.chdir(tools)
    try:
        from mssf_examples.openpcdet import register
        from mssf_examples.openpcdet.__main__ import main

        register()
        main(["create_vod_infos", "cfgs/dataset_configs/vod_radar5_dataset.yaml", "--data_path",
              f"{BASE}/radar_5frames", "--workers", "1"])
        shutil.copytree(Path(BASE) / "radar_5frames", Path(BASE) / "radar",
                        ignore=shutil.ignore_patterns("*.pkl"))  # single scan: same frames, infos not built
        yield tools
    finally:
        os.chdir(cwd)


def cfg_for(data_path):
    cfg = load("second_radar")
    cfg.DATA_CONFIG.DATA_PATH = data_path
    return cfg


def loader(cfg, training=True):
    from pcdet.datasets import build_dataloader

    dataset, loader, _ = build_dataloader(cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=2, dist=False, workers=0,
                                          training=training, seed=0)
    return dataset, loader


def test_the_infos_folder_loads(tools):
    dataset, _ = loader(cfg_for(f"{BASE}/radar_5frames"))
    assert len(dataset) == 2 and dataset.kitti_infos[0]["point_cloud"]["sensor_folder"] == "radar_5frames"


@pytest.mark.parametrize("training", [True, False])
def test_data_path_without_the_infos_names_the_folder_they_were_built_for(tools, training):
    with pytest.raises(MSSFError, match=r"INFO_PATH\['(train|test)'\]: \['vod_infos_(train|val).pkl'\] not found in "
                                        r"DATA_PATH '\.\./data/vod_checks/radar'.*they are in .*radar_5frames'\]: the infos were built for "
                                        r"that folder"):
        loader(cfg_for(f"{BASE}/radar"), training=training)


def test_infos_of_another_sensor_folder_are_refused(tools):
    shutil.copy(Path(BASE) / "radar_5frames" / "vod_infos_train.pkl", Path(BASE) / "radar" / "vod_infos_train.pkl")
    try:
        with pytest.raises(MSSFError, match=r"built for the sensor folder \['radar_5frames'\] .*not 'radar'"):
            loader(cfg_for(f"{BASE}/radar"))
    finally:
        (Path(BASE) / "radar" / "vod_infos_train.pkl").unlink()
    renamed = Path(BASE) / "my_radar5"  # a renamed copy keeps its (valid) infos
    shutil.copytree(Path(BASE) / "radar_5frames", renamed)
    try:
        assert len(loader(cfg_for(str(renamed)))[0]) == 2
    finally:
        shutil.rmtree(renamed)


def test_any_split_without_frames_says_why(tools, tmp_path):
    with pytest.raises(MSSFError, match=r"DATA_PATH '\.\./data/vod_nowhere/radar_5frames'.*no such folder.*tools/"):
        loader(cfg_for("../data/vod_nowhere/radar_5frames"))
    cfg = cfg_for(f"{BASE}/radar_5frames")
    cfg.DATA_CONFIG.INFO_PATH = {"train": ["vod_infos_empty.pkl"], "test": ["vod_infos_val.pkl"]}
    (Path(BASE) / "radar_5frames" / "vod_infos_empty.pkl").write_bytes(pickle.dumps([]))
    with pytest.raises(MSSFError, match=r"\['vod_infos_empty.pkl'\] in DATA_PATH .* hold no frame"):
        loader(cfg)
    cfg.DATA_CONFIG.INFO_PATH = {"train": [], "test": ["vod_infos_val.pkl"]}
    with pytest.raises(MSSFError, match=r"INFO_PATH\['train'\]: no info file listed"):
        loader(cfg)


def test_4_float_points_whose_size_divides_by_7_are_refused(tools):
    """A lidar-like x, y, z, reflectance file of 7 k points (28 k floats: 4 k rows of 7) is not VoD radar."""
    dataset, _ = loader(cfg_for(f"{BASE}/radar_5frames"))
    fid = dataset.kitti_infos[0]["point_cloud"]["lidar_idx"]
    good = dataset.get_lidar(fid)
    assert good.shape[1] == 7 and len(good) > 0  # generated 5-scan points pass (time 0 .. -4)
    path = dataset.root_split_path / "velodyne" / f"{fid}.bin"
    saved = path.read_bytes()
    rng = np.random.default_rng(0)
    n = 7 * 300
    lidar = np.stack([rng.uniform(2, 70, n), rng.uniform(-30, 30, n), rng.uniform(-2, 1, n), rng.uniform(0, 1, n)], 1)
    try:
        path.write_bytes(lidar.astype(np.float32).tobytes())
        with pytest.raises(MSSFError, match=r"'time' column reaches .*another layout or dtype \(4 columns: 2100 points"):
            dataset.get_lidar(fid)
        with pytest.raises(MSSFError, match="another layout"):
            next(iter(loader(cfg_for(f"{BASE}/radar_5frames"))[1]))  # through OpenPCDet's __getitem__
    finally:
        path.write_bytes(saved)


def test_real_vod_radar_frames_pass(openpcdet, realdata_root):
    from mssf_examples.openpcdet.vod_dataset import check_vod_points

    for path in sorted((realdata_root / "vod" / "radar" / "velodyne").glob("*.bin")):
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 7)
        assert check_vod_points(pts, path) is pts


def test_empty_point_file_passes(openpcdet):
    from mssf_examples.openpcdet.vod_dataset import check_vod_points

    assert check_vod_points(np.zeros((0, 7), np.float32), "x.bin").shape == (0, 7)
    with pytest.raises(MSSFError, match="non-finite"):
        check_vod_points(np.full((2, 7), np.nan, np.float32), "x.bin")
