"""Single-scan View-of-Delft (VoD's ``radar`` folder) in OpenPCDet: ``dataset_configs/vod_radar_dataset.yaml``.

The VoD set-up of test_openpcdet_vod.py (its module fixture ``tools``) plus a generated ``radar`` tree (the same
scenes' points with ``time`` 0, as a single scan has) beside its ``radar_5frames``; infos from the documented
``create_vod_infos`` line with this config; then models whose ``_BASE_CONFIG_`` names it, as docs/frameworks.md
says, train two steps through OpenPCDet's ``train_one_epoch`` and evaluate with the VoD protocol: the MSSF model of
each detector kind (SECOND, VoxelNeXt, CenterPoint, PointPillars, VoxelNeXt-2D: each reads the points, images and
calibration through the same dataset, but each kind voxelises, fuses and assigns targets on its own grid) and a
radar-only twin (no image read), each shrunk as its own tests shrink it (``openpcdet_models.shrink``).
"""

from __future__ import annotations

import logging
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
from openpcdet_models import shrink  # noqa: E402
from test_openpcdet_centerpoint import keep_all_boxes  # noqa: E402
from test_openpcdet_vod import build, tools, train  # noqa: E402,F401  (tools: the module fixture)

pytestmark = pytest.mark.usefixtures("one_thread")
#: one MSSF model per detector kind, and a radar-only twin
MODELS = ("mssf_second", "mssf_voxelnext", "mssf_centerpoint", "mssf_pointpillar", "mssf_voxelnext2d", "second_radar")


@pytest.fixture(scope="module")
def single_scan(tools):
    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.openpcdet.__main__ import main
    from mssf_examples.scenes.synthetic import generate_scene, scene_seed

    splits = {s: [generate_scene(scene_seed(1, s, i)) for i in range(n)] for s, n in (("train", 4), ("val", 2))}
    data = tools.root.parent / "data" / "view_of_delft"
    write_vod_tree(data, splits, sensor="radar", image_format="jpg")
    for f in (data / "radar" / "training" / "velodyne").iterdir():  # one scan: time 0 on every point
        p = np.fromfile(f, dtype="<f4").reshape(-1, 7)
        p[:, 6] = 0.0
        p.tofile(f)
    main(["create_vod_infos", "cfgs/dataset_configs/vod_radar_dataset.yaml"])  # the config's own comment line
    for name in MODELS:  # each on the single-scan config (docs/frameworks.md)
        text = (tools.root / "cfgs" / "vod_models" / f"{name}.yaml").read_text()
        single = text.replace("vod_radar5_dataset.yaml", "vod_radar_dataset.yaml")
        assert single != text
        (tools.root / "cfgs" / "vod_models" / f"{name}_single_scan.yaml").write_text(single)
    return data / "radar"


def test_single_scan_config_is_the_5_scan_one_at_radar(tools):
    from easydict import EasyDict
    from pcdet.config import cfg_from_yaml_file

    one, five = (cfg_from_yaml_file(f"cfgs/dataset_configs/{n}.yaml", EasyDict())
                 for n in ("vod_radar_dataset", "vod_radar5_dataset"))
    assert one.DATA_PATH == "../data/view_of_delft/radar" and five.DATA_PATH == "../data/view_of_delft/radar_5frames"
    one.pop("DATA_PATH"), five.pop("DATA_PATH")
    assert one == five


@pytest.mark.parametrize("name", MODELS)
def test_trains_and_evaluates_on_single_scan_radar(single_scan, tools, name, tmp_path):
    from eval_utils.eval_utils import eval_one_epoch

    torch.manual_seed(0)
    cfg = shrink(f"{name}_single_scan", tools.ckpt)
    dataset, loader, model = build(cfg)
    assert Path(dataset.root_path).resolve() == single_scan.resolve()
    assert {i["point_cloud"]["sensor_folder"] for i in dataset.kitti_infos} == {"radar"}
    assert float(np.abs(dataset.get_lidar(dataset.kitti_infos[0]["point_cloud"]["lidar_idx"])[:, 6]).max()) == 0.0
    seen = train(cfg, model, loader)
    assert len(seen) == 2 and all(np.isfinite(loss) for loss, _ in seen)
    assert all(("loss_mssf_seg" in tb) == name.startswith("mssf") for _, tb in seen)  # the fusion ran (or not)
    if "NMS_CONFIG" in cfg.MODEL.POST_PROCESSING:  # the anchor head: fewer of the untrained head's boxes into NMS
        cfg.MODEL.POST_PROCESSING.NMS_CONFIG.NMS_PRE_MAXSIZE = 256
    _, test_loader, _ = build(keep_all_boxes(cfg), training=False)
    model.eval()
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, test_loader, epoch_id="0", logger=logging.getLogger("eval"),
                         result_dir=tmp_path)
    assert {"entire_area/mAP3D_R40", "driving_corridor/mAP3D_R40"} <= set(ret)
