"""TJ4DRadSet in OpenPCDet: ``TJ4DDataset``, its infos command, the ``tj4d_models/`` configs, the TJ4D protocol.

A generated TJ4DRadSet tree (``tests/integrations/mmdet3d_vod_tree.write_tj4d_tree``: 8-float points,
``.png`` images, the four classes with a ``Truck`` in every frame; 2 training and 2 validation frames,
304 x 484 images) is written under OpenPCDet's ``data/TJ4DRadSet``, its infos come from the documented
``python -m mssf_examples.openpcdet create_tj4d_infos`` (docs/frameworks.md's line, run as printed, as are
its ``train.py`` / ``test.py`` lines with CPU sizes), and every TJ4D model config (five detector kinds: SECOND,
VoxelNeXt, CenterPoint, PointPillars, VoxelNeXt-2D, each with its radar-only twin, shrunk as their VoD tests
shrink them: ``openpcdet_models.shrink``) trains two steps through OpenPCDet's ``train_one_epoch`` and evaluates
through ``eval_one_epoch`` with the dataset's ``evaluation()``. Each TJ4D file is its ``vod_models/`` twin but
for the keys TJ4D needs (the pillar files checked against the mmdetection3d TJ4D MSSF-PP config too), and each
MSSF file less its fusion is its radar-only twin. That evaluation is compared with the project's TJ4D evaluation
(``evaluate(protocol="tj4d")``, the authors' ``eval_tj4d`` rules, checked against their code in
tests/examples/evaluation) run on the label files and on detection files written from the same boxes.
"""

from __future__ import annotations

import copy
import logging
import pickle
import re
import shlex
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import write_tj4d_tree  # noqa: E402
from openpcdet_models import PILLARS, TWINS, shrink  # noqa: E402
from test_openpcdet_centerpoint import keep_all_boxes  # noqa: E402
from test_openpcdet_vod import CONFIGS, _line, build, load, small, tools, train  # noqa: E402,F401  (tools: fixture)

from mssf_blocks import MSSFError  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
CLASSES = ["Car", "Pedestrian", "Cyclist", "Truck"]
MODELS = ("mssf_second", "second_radar", "mssf_voxelnext", "voxelnext_radar", "mssf_centerpoint", "centerpoint_radar",
          *PILLARS)
MMDET3D_PILLARS = Path(__file__).resolve().parents[2] / "examples" / "configs" / "mmdet3d" / "_base_" / "models" / \
    "mssf_pointpillars_tj4d.py"
REGIONS = ("range_0_50", "range_0_70", "range_all")


@pytest.fixture(scope="module")
def tj4d(tools):
    """OpenPCDet's tools/ (the VoD fixture: cwd, classes registered, the image-branch checkpoint) with the
    tj4d_models/ configs, a generated TJ4DRadSet tree in ../data/TJ4DRadSet and its OpenPCDet infos."""
    from mssf_examples.openpcdet.__main__ import main

    shutil.copytree(CONFIGS / "tj4d_models", tools.root / "cfgs" / "tj4d_models", dirs_exist_ok=True)
    root = write_tj4d_tree(tools.root.parent / "data" / "TJ4DRadSet", mmdet3d_infos=False)
    (command,) = documented_lines("create_tj4d_infos")
    main(shlex.split(command)[3:])  # docs/frameworks.md's line, as printed
    return types.SimpleNamespace(root=root, ckpt=tools.ckpt)


def documented_lines(word):
    """The ``python -m mssf_examples.openpcdet`` lines of docs/frameworks.md's "TJ4DRadSet in OpenPCDet" holding
    ``word``."""
    text = (Path(__file__).resolve().parents[2] / "docs" / "frameworks.md").read_text()
    section = text.split("### TJ4DRadSet in OpenPCDet", 1)[1].split("\n### ", 1)[0]
    return [line for block in re.findall(r"```bash\n(.*?)```", section, flags=re.S)
            for line in block.replace("\\\n", " ").splitlines() if word in line]


def tj4d_small(name, ckpt):
    if name in PILLARS:  # 0.32 m pillars: 216 x 248, PointPillars' three stride-2 blocks halve and double back
        return shrink(name, ckpt, "tj4d_models")
    cfg = small(name, ckpt, folder="tj4d_models")
    # 176 x 160 voxels: SECOND's / CenterPoint's BEV at stride 8 must halve and double back to the same size
    # (80 m / 0.4 m / 8 = 25 would not; the shipped 0.05 m gives 1408 x 1600, 176 x 200 at stride 8)
    cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE = [0.4, 0.5, 0.125]
    return cfg


def _without(cfg, drop):
    """``cfg`` as a plain dict less the dotted keys in ``drop``."""
    out = copy.deepcopy(dict(cfg))
    for key in drop:
        *path, last = key.split(".")
        d = out
        for p in path:
            d = d.get(p, {})
        d.pop(last, None)
    return out


def test_tj4d_configs_are_the_vod_ones_with_tj4d_data(tj4d):
    """Each tj4d_models/ config = its vod_models/ twin except the dataset config, the classes, the anchor sizes (the
    truck's anchor otherwise the car's), the centre limits and EVAL_METRIC, and for the pillar files the pillar
    range and height; the TJ4D values are the paper's (the presets of the examples)."""
    from mssf_examples.models.heads.anchor_head import TJ4D_ANCHOR_SIZES
    from mssf_examples.models.presets import TJ4D

    differs = ["DATA_CONFIG", "CLASS_NAMES", "MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG",
               "MODEL.DENSE_HEAD.CLASS_NAMES_EACH_HEAD", "MODEL.DENSE_HEAD.POST_PROCESSING.POST_CENTER_LIMIT_RANGE",
               "MODEL.POST_PROCESSING.EVAL_METRIC"]
    for name in MODELS:
        cfg, vod = load(name, "tj4d_models"), load(name)
        assert _without(cfg, differs) == _without(vod, differs), name
        assert cfg.CLASS_NAMES == CLASSES == list(TJ4D.class_names)
        d, vod_d = cfg.DATA_CONFIG, copy.deepcopy(vod.DATA_CONFIG)
        assert d.DATASET == "TJ4DDataset"
        if name in PILLARS:  # the paper's pillar range (a multiple of 0.16 m), a pillar as high as the range
            pcr = list(TJ4D.pillar_range)
            assert d.POINT_CLOUD_RANGE == pcr
            assert d.DATA_PROCESSOR[-1].VOXEL_SIZE == [*TJ4D.pillar_size, pcr[5] - pcr[2]]
            vod_d.DATA_PROCESSOR[-1].VOXEL_SIZE[2] = pcr[5] - pcr[2]
        else:
            assert d.POINT_CLOUD_RANGE == list(TJ4D.point_cloud_range)
            assert d.DATA_PROCESSOR[-1].VOXEL_SIZE == list(TJ4D.voxel_size)
        assert d.POINT_FEATURE_ENCODING.used_feature_list == ["x", "y", "z", "v_r", "power"]
        data_keys = ["_BASE_CONFIG_", "DATASET", "DATA_PATH", "POINT_CLOUD_RANGE", "IMAGE_FILE_EXTENSION", "INFO_PATH",
                     "POINT_FEATURE_ENCODING"]
        assert _without(d, data_keys) == _without(vod_d, data_keys), name
        head = cfg.MODEL.DENSE_HEAD
        if "ANCHOR_GENERATOR_CONFIG" in head:
            anchors = head.ANCHOR_GENERATOR_CONFIG
            assert [a["class_name"] for a in anchors] == CLASSES
            assert [tuple(a["anchor_sizes"][0]) for a in anchors] == list(TJ4D_ANCHOR_SIZES)
            vod_anchors = vod.MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG
            for a, v in zip(anchors, [*vod_anchors, vod_anchors[0]]):  # the rest as VoD's; the truck's as the car's
                assert _without(a, ["class_name", "anchor_sizes"]) == _without(v, ["class_name", "anchor_sizes"]), name
        else:
            assert head.CLASS_NAMES_EACH_HEAD == [CLASSES]


def test_tj4d_pillar_configs_are_the_mmdet3d_mssf_pp_ones(tj4d):
    """MSSF-PP and its twin on TJ4D = the mmdetection3d TJ4D MSSF-PP model config (mssf_pointpillars_tj4d.py, read
    by mmengine with its ``_base_``): pillar range and size, input features, anchor sizes, bottoms and rotations,
    the assigners' IoU thresholds."""
    config = pytest.importorskip("mmengine.config")
    mm = config.Config.fromfile(str(MMDET3D_PILLARS)).model
    enc, gen = mm.pts_middle_encoder, mm.pts_bbox_head.anchor_generator
    assigners = mm.train_cfg.pts.assigner
    for name in PILLARS:
        cfg = load(name, "tj4d_models")
        d = cfg.DATA_CONFIG
        assert d.POINT_CLOUD_RANGE == list(enc.point_cloud_range) and d.DATA_PROCESSOR[-1].VOXEL_SIZE == enc.voxel_size
        assert len(d.POINT_FEATURE_ENCODING.used_feature_list) == enc.in_channels == 5
        if "voxelnext2d" in name:
            continue  # (a centre head: no anchors)
        anchors = cfg.MODEL.DENSE_HEAD.ANCHOR_GENERATOR_CONFIG
        assert [a["anchor_sizes"][0] for a in anchors] == gen.sizes
        assert [a["anchor_bottom_heights"][0] for a in anchors] == [r[2] for r in gen.ranges]
        assert all(a["anchor_rotations"] == gen.rotations for a in anchors)
        assert [(a["matched_threshold"], a["unmatched_threshold"]) for a in anchors] == [
            (s.pos_iou_thr, s.neg_iou_thr) for s in assigners]


def _pillar_twin(cfg):
    """A pillar MSSF config as its radar-only twin reads: no image branch, no images read, no fusion key (MSSF-PP's
    twin is OpenPCDet's own PointPillar and BaseBEVBackbone; VoxelNeXt-2D's keeps the backbone at 0 fusion blocks)."""
    cfg = copy.deepcopy(cfg)
    cfg.MODEL.pop("IMAGE_BRANCH")
    cfg.DATA_CONFIG.GET_ITEM_LIST = ["points"]
    if cfg.MODEL.NAME == "MSSFPointPillar":
        b = cfg.MODEL.BACKBONE_2D
        cfg.MODEL.NAME = "PointPillar"
        cfg.MODEL.BACKBONE_2D = type(b)({k: b[k] for k in ("LAYER_NUMS", "LAYER_STRIDES", "NUM_FILTERS",
                                                             "UPSAMPLE_STRIDES", "NUM_UPSAMPLE_FILTERS")},
                                        NAME="BaseBEVBackbone")
    else:
        cfg.MODEL.BACKBONE_3D = type(cfg.MODEL.BACKBONE_3D)(NAME=cfg.MODEL.BACKBONE_3D.NAME, NUM_FUSION_BLOCKS=0)
    return cfg


@pytest.mark.parametrize("folder", ["vod_models", "tj4d_models"])
@pytest.mark.parametrize("name", ["mssf_pointpillar", "mssf_voxelnext2d"])
def test_pillar_fusion_removed_is_the_radar_only_twin_config(tj4d, name, folder):
    """As test_openpcdet_centerpoint.py's twin check of the voxel configs (both folders), for the pillar ones."""
    assert _pillar_twin(load(name, folder)) == load(TWINS[name], folder)


def test_infos_and_dataset_read_8_float_points_png(tj4d):
    cfg = tj4d_small("mssf_second", tj4d.ckpt)
    dataset, loader, _ = build(cfg, training=False)
    assert len(dataset) == 2
    info = dataset.kitti_infos[0]
    fid = info["point_cloud"]["lidar_idx"]
    raw = np.fromfile(tj4d.root / "training" / "velodyne" / f"{fid}.bin", dtype=np.float32).reshape(-1, 8)
    assert info["point_cloud"]["num_features"] == 8
    np.testing.assert_array_equal(dataset.get_lidar(fid), raw)
    assert tuple(info["image"]["image_shape"]) == (304, 484)  # from the .png
    names = list(info["annos"]["name"])
    assert "Truck" in names and "Car" in names
    with open(tj4d.root / "tj4d_infos_train.pkl", "rb") as f:
        assert len(pickle.load(f)) == 2
    assert (tj4d.root / "tj4d_infos_trainval.pkl").is_file()
    batch = next(iter(loader))
    assert batch["points"].shape[1] == 1 + 5 and batch["images"].shape[1:] == (304, 484, 3)


def test_a_vod_file_is_refused_as_tj4d_points(tj4d, tmp_path):
    from mssf_examples.openpcdet.tj4d_dataset import check_tj4d_points

    vod = np.random.default_rng(0).normal(size=(8, 7)).astype(np.float32)  # 56 floats: 7 rows of 8
    vod[:, 6] = 0.0
    with pytest.raises(MSSFError, match="TJ4DRadSet's 8 float32 columns.*'range'"):
        check_tj4d_points(vod.reshape(-1, 8), tmp_path / "00000.bin")
    good = np.fromfile(next((tj4d.root / "training" / "velodyne").iterdir()), dtype=np.float32).reshape(-1, 8)
    assert check_tj4d_points(good, "x") is good


@pytest.mark.parametrize("name", MODELS)
def test_trains_and_evaluates_with_the_tj4d_protocol(tj4d, name, tmp_path):
    from eval_utils.eval_utils import eval_one_epoch

    torch.manual_seed(0)
    cfg = tj4d_small(name, tj4d.ckpt)
    _, loader, model = build(cfg)
    fusion = name.startswith("mssf")
    assert (getattr(model, "image_branch", None) is not None) == fusion  # (pointpillar_radar: OpenPCDet's PointPillar)
    seen = train(cfg, model, loader, epochs=2)
    assert len(seen) == 2
    for loss, tb in seen:
        assert np.isfinite(loss) and ("loss_mssf_seg" in tb) == fusion
    if fusion:
        if name in PILLARS:  # the fusion stages of MSSFBaseBEVBackbone / the VoxelNeXt-2D backbone
            backbone = model.backbone_2d if model.backbone_3d is None else model.backbone_3d
            grads = [p.grad for p in backbone.stages.parameters()]
        else:
            grads = [p.grad for n, p in model.backbone_3d.named_parameters() if ".fusion." in n]
        assert grads and all(g is not None for g in grads)
    if "NMS_CONFIG" in cfg.MODEL.POST_PROCESSING:  # the anchor head: fewer of the untrained head's boxes into NMS
        cfg.MODEL.POST_PROCESSING.NMS_CONFIG.NMS_PRE_MAXSIZE = 256
    _, test_loader, _ = build(keep_all_boxes(cfg), training=False)
    model.eval()
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, test_loader, epoch_id="0", logger=logging.getLogger("eval"),
                         result_dir=tmp_path)
    for region in REGIONS:
        assert {f"{region}/{c}_AP3D_R40" for c in CLASSES} | {f"{region}/mAP3D_R40"} <= set(ret), sorted(ret)
    assert "entire_area/mAP3D_R40" not in ret


def test_tj4d_evaluation_equals_the_protocol_on_the_label_files(tj4d, tmp_path):
    """dataset.evaluation() on OpenPCDet-style det_annos = ``evaluate(protocol="tj4d")`` on the label files and on
    detection files holding the same boxes (KITTI lines with a score), read by the project's KITTI reader."""
    from mssf_examples.data.kitti_io import read_labels
    from mssf_examples.evaluation.metrics import evaluate

    dataset, _, _ = build(tj4d_small("second_radar", tj4d.ckpt), training=False)
    rng = np.random.default_rng(0)
    gts, preds, det_annos = [], [], []
    for info in dataset.kitti_infos:
        fid = info["point_cloud"]["lidar_idx"]
        gts.append(read_labels(tj4d.root / "training" / "label_2" / f"{fid}.txt"))
        a = info["annos"]
        keep = np.flatnonzero(np.isin(a["name"], CLASSES))
        n = len(keep)
        d = {k: np.asarray(a[k], dtype=np.float64)[keep] for k in ("truncated", "occluded", "alpha", "bbox",
                                                                    "dimensions", "location", "rotation_y")}
        d["location"] = d["location"] + rng.normal(0, 0.15, (n, 3))  # near misses and hits
        d["dimensions"] = d["dimensions"] * rng.uniform(0.85, 1.15, (n, 3))
        d["bbox"] = d["bbox"] + rng.normal(0, 3, (n, 4))
        d["name"] = np.where(rng.uniform(size=n) < 0.15, "Car", a["name"][keep])  # some wrong classes
        d["score"] = rng.uniform(0.05, 1.0, n)
        d["frame_id"] = fid
        det_annos.append(d)
        path = tmp_path / f"{fid}.txt"
        path.write_text("".join(_line(d, k, d["score"][k]) + "\n" for k in range(n)))
        preds.append(read_labels(path))
    _, ours = dataset.evaluation(det_annos, CLASSES)
    theirs = evaluate(preds, gts, CLASSES, protocol="tj4d")
    compared = 0
    for region in REGIONS:
        for cname in CLASSES:
            for key in ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40"):
                mine, ref = ours[f"{region}/{cname}_{key}"], theirs[region][cname][key]
                if np.isnan(ref):
                    assert np.isnan(mine), (region, cname, key)
                    continue
                assert mine == pytest.approx(ref, abs=1e-6), (region, cname, key, mine, ref)
                compared += 1
    values = [theirs[r][c]["AP3D_R40"] for r in REGIONS for c in CLASSES]
    # (with a few GTs per class the protocol fills only as many of its 41 recall slots: small APs here)
    assert compared == 48 and 0 < max(values) < 100  # every class present, neither empty nor perfect
    assert theirs["range_0_70"]["Truck"]["APBEV_R40"] > 0


def test_documented_train_and_test_commands_run(tj4d, monkeypatch):
    """docs/frameworks.md's TJ4DRadSet ``train.py`` and ``test.py`` lines, from tools/, with CPU sizes given through
    OpenPCDet's own options (as test_openpcdet_vod.py runs the VoD ones): one epoch, then the saved checkpoint
    evaluated with the TJ4D protocol."""
    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.openpcdet.__main__ import main

    monkeypatch.setattr("time.sleep", lambda seconds: None)  # repeat_eval_ckpt waits 30 s for new checkpoints
    ckpt = tj4d.root.parents[1] / "checkpoints" / "htc_r50_fpn_image_branch.pth"  # the config's CHECKPOINT
    ckpt.parent.mkdir(exist_ok=True)
    torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=256, num_outs=4).state_dict(), ckpt)
    # batch size 1: two steps over the two training frames (one-cycle's warm-up needs more than one)
    cpu = ["--workers", "0", "--batch_size", "1", "--set", "MODEL.IMAGE_BRANCH.DEPTH", "18",
           "MODEL.IMAGE_BRANCH.BASE_CHANNELS", "8", "OPTIMIZATION.PCT_START", "0.5"]
    (train_line,) = documented_lines("train.py --cfg_file cfgs/tj4d")
    (test_line,) = documented_lines("test.py")
    main(["--pure-torch-nms", *shlex.split(train_line)[3:], "--epochs", "1", "--wo_gpu_stat", *cpu])
    out = tj4d.root.parents[1] / "output" / "tj4d_models" / "mssf_voxelnext" / "default"
    assert (out / "ckpt" / "checkpoint_epoch_1.pth").is_file()
    log = "".join(p.read_text() for p in out.glob("*.log"))
    assert "TJ4D range_0_50:" in log and "TJ4D range_all:" in log, log[-2000:]
    main(["--pure-torch-nms", *shlex.split(test_line.replace("checkpoint_epoch_80", "checkpoint_epoch_1"))[3:], *cpu])
    logs = list((out / "eval").rglob("log_eval_*.txt"))
    assert logs and "TJ4D range_0_70:" in logs[-1].read_text()
