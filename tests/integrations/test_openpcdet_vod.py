"""MSSF-SECOND / MSSF-VoxelNeXt on View-of-Delft through OpenPCDet's own code (the ``openpcdet`` fixture).

A generated VoD release tree (radar_5frames, ``.jpg`` images, 7-float points, VoD calib and labels)
is written under OpenPCDet's ``data/``; the shipped YAMLs are copied into ``tools/cfgs/`` and read by
``cfg_from_yaml_file`` from ``tools/``; infos come from ``python -m mssf_examples.openpcdet
create_vod_infos``; then OpenPCDet's ``build_dataloader``, ``build_network``, ``build_optimizer``,
``train_one_epoch`` (with ``model_fn_decorator``) and ``eval_one_epoch`` run. On this CPU-only machine
``torch.Tensor.cuda`` is the identity (``load_data_to_gpu`` and the heads' own ``.cuda()`` calls) and
the CUDA NMS / IoU are the project's pure-torch ones (``register(pure_torch_box_ops=True)``). Sizes are
shrunk for the CPU (coarser voxels, a ResNet-18 of width 8 with 16-channel FPN levels).
"""

from __future__ import annotations

import copy
import logging
import os
import shutil
import types
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

from mssf_blocks import MSSFError  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
CONFIGS = Path(__file__).resolve().parents[2] / "examples" / "configs" / "openpcdet"
MODELS = ("mssf_second", "second_radar", "mssf_voxelnext", "voxelnext_radar", "mssf_centerpoint", "centerpoint_radar")


@pytest.fixture(scope="module")
def tools(openpcdet, tmp_path_factory):
    """OpenPCDet's tools/ as cwd, with our configs, a generated VoD tree and its infos; classes registered."""
    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import generate_scene, scene_seed

    tools = openpcdet / "tools"
    shutil.copytree(CONFIGS / "dataset_configs", tools / "cfgs" / "dataset_configs", dirs_exist_ok=True)
    shutil.copytree(CONFIGS / "vod_models", tools / "cfgs" / "vod_models", dirs_exist_ok=True)
    splits = {s: [generate_scene(scene_seed(0, s, i)) for i in range(n)] for s, n in (("train", 4), ("val", 2))}
    write_vod_tree(openpcdet / "data" / "view_of_delft", splits, sensor="radar_5frames", image_format="jpg")
    cwd, cuda = os.getcwd(), torch.Tensor.cuda
    os.chdir(tools)
    torch.Tensor.cuda = lambda self, *args, **kwargs: self  # CPU only: load_data_to_gpu, the heads' .cuda()
    try:
        from mssf_examples.openpcdet import register
        from mssf_examples.openpcdet.__main__ import main

        register(pure_torch_box_ops=True)
        main(["create_vod_infos", "cfgs/dataset_configs/vod_radar5_dataset.yaml"])  # the documented command
        ckpt = tmp_path_factory.mktemp("ckpt") / "image_branch.pth"
        from mssf_examples.models.image_branch import ImageBranch

        torch.manual_seed(0)
        branch = ImageBranch(depth=18, base_channels=8, fpn_channels=16, num_outs=4)
        # an mmdet-style checkpoint: img_backbone.* / img_neck.* (renamed by CHECKPOINT_PREFIXES)
        state = {k.replace("backbone.", "img_backbone.", 1).replace("neck.", "img_neck.", 1): v
                 for k, v in branch.state_dict().items()}
        torch.save({"state_dict": state}, ckpt)
        yield types.SimpleNamespace(root=tools, ckpt=ckpt, branch=branch)
    finally:
        torch.Tensor.cuda = cuda
        os.chdir(cwd)


def load(name, folder="vod_models"):
    from easydict import EasyDict
    from pcdet.config import cfg_from_yaml_file

    cfg = EasyDict()
    cfg_from_yaml_file(f"cfgs/{folder}/{name}.yaml", cfg)
    cfg.LOCAL_RANK = 0
    return cfg


def small(name, ckpt, folder="vod_models"):
    """The shipped config, shrunk for the CPU (no setting the tests check is changed)."""
    cfg = load(name, folder)
    cfg.DATA_CONFIG.DATA_PROCESSOR[-1].VOXEL_SIZE = [0.4, 0.4, 0.125]  # 128 x 128 x 40
    m = cfg.MODEL
    if "IMAGE_BRANCH" in m:
        m.IMAGE_BRANCH.update(DEPTH=18, BASE_CHANNELS=8, FPN_CHANNELS=16, CHECKPOINT=str(ckpt))
    m.BACKBONE_3D.update(IMAGE_CHANNELS=[16] * 4, MSDFF_HEADS=2, MSDFF_POINTS=2, SEG_HIDDEN=[16])
    if m.NAME in ("MSSFSECONDNet", "MSSFCenterPoint"):
        m.BACKBONE_2D.update(LAYER_NUMS=[1, 1], NUM_FILTERS=[32, 64], NUM_UPSAMPLE_FILTERS=[32, 32])
        if m.NAME == "MSSFCenterPoint":
            m.DENSE_HEAD.SHARED_CONV_CHANNEL = 16
            m.DENSE_HEAD.POST_PROCESSING.MAX_OBJ_PER_SAMPLE = 100  # at most the 16 x 16 BEV cells (top-k)
    else:
        m.BACKBONE_3D.update(CHANNELS=[8, 8, 16, 16, 32, 32, 32], OUT_CHANNELS=32)
        m.DENSE_HEAD.update(INPUT_FEATURES=32, SHARED_CONV_CHANNEL=32)
        # MAX_OBJ_PER_SAMPLE stays 500, above a frame's BEV voxels on this coarse grid (the stock head
        # could not decode that: test_openpcdet_sparse_frames.py)
    cfg.OPTIMIZATION.BATCH_SIZE_PER_GPU = 2
    return cfg


def build(cfg, training=True):
    from pcdet.datasets import build_dataloader
    from pcdet.models import build_network

    dataset, loader, _ = build_dataloader(cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=2, dist=False, workers=0,
                                          training=training, seed=0)
    model = build_network(cfg.MODEL, num_class=len(cfg.CLASS_NAMES), dataset=dataset)
    return dataset, loader, model


def train(cfg, model, loader, epochs=1):
    """OpenPCDet's train_one_epoch with model_fn_decorator; returns [(loss, tb_dict)] per step."""
    from pcdet.models import model_fn_decorator
    from train_utils.optimization import build_optimizer, build_scheduler
    from train_utils.train_utils import train_one_epoch

    optimizer = build_optimizer(model, cfg.OPTIMIZATION)
    # one-cycle over at least 3 epochs: its warm-up phase would be empty over 2 steps (division by zero)
    scheduler, _ = build_scheduler(optimizer, total_iters_each_epoch=len(loader), total_epochs=max(epochs, 3),
                                   last_epoch=-1, optim_cfg=cfg.OPTIMIZATION)
    model_fn, seen = model_fn_decorator(), []

    def model_func(model, batch):
        out = model_fn(model, batch)
        seen.append((float(out.loss), dict(out.tb_dict)))
        return out

    import tqdm

    model.train()
    it = 0
    with tqdm.trange(epochs, desc="epochs", disable=True) as tbar:  # train_model's epoch bar
        for epoch in tbar:
            it = train_one_epoch(model, optimizer, loader, model_func, scheduler, accumulated_iter=it,
                                 optim_cfg=cfg.OPTIMIZATION, rank=0, tbar=tbar, total_it_each_epoch=len(loader),
                                 dataloader_iter=iter(loader), cur_epoch=epoch, total_epochs=epochs)
    return seen


def test_shipped_configs_have_the_paper_vod_settings(tools):
    for name in MODELS:
        cfg = load(name)
        d = cfg.DATA_CONFIG
        assert d.DATASET == "VoDDataset" and cfg.CLASS_NAMES == ["Car", "Pedestrian", "Cyclist"]
        assert d.POINT_CLOUD_RANGE == [0, -25.6, -3, 51.2, 25.6, 2]
        assert d.DATA_PROCESSOR[-1].VOXEL_SIZE == [0.05, 0.05, 0.125]
        assert len(d.POINT_FEATURE_ENCODING.used_feature_list) == 7
        assert [a.NAME for a in d.DATA_AUGMENTOR.AUG_CONFIG_LIST] == list(cfg.MODEL.BACKBONE_3D.AUG_ORDER) == [
            "random_world_flip", "random_world_rotation", "random_world_scaling"]
        o = cfg.OPTIMIZATION
        assert (o.OPTIMIZER, o.LR) == ("adam_onecycle", 0.001)
        fusion = name.startswith("mssf")
        assert (cfg.MODEL.BACKBONE_3D.NUM_FUSION_BLOCKS > 0) == fusion and ("IMAGE_BRANCH" in cfg.MODEL) == fusion
        assert ("images" in d.GET_ITEM_LIST) == fusion
        if fusion:
            assert cfg.MODEL.IMAGE_BRANCH.FROZEN is True and cfg.MODEL.IMAGE_BRANCH.DEPTH == 50
    # MSSF-V: OpenPCDet's VoxelResBackBone8xVoxelNeXt widths (16, 32, 64, 128, 128, 128) doubled
    assert load("mssf_voxelnext").MODEL.BACKBONE_3D.CHANNELS == [32, 32, 64, 128, 256, 256, 256]


def test_vod_dataset_reads_7_float_points_jpg_and_infos(tools):
    cfg = small("mssf_second", tools.ckpt)
    dataset, loader, _ = build(cfg, training=False)
    info = dataset.kitti_infos[0]
    fid = info["point_cloud"]["lidar_idx"]
    raw = np.fromfile(dataset.root_split_path / "velodyne" / f"{fid}.bin", dtype=np.float32).reshape(-1, 7)
    assert info["point_cloud"]["num_features"] == 7
    np.testing.assert_array_equal(dataset.get_lidar(fid), raw)
    assert tuple(info["image"]["image_shape"]) == (152, 240)  # from the .jpg
    assert (info["annos"]["num_points_in_gt"][info["annos"]["index"] >= 0] >= 0).all()
    batch = next(iter(loader))
    assert batch["points"].shape[1] == 1 + 7 and batch["images"].shape[1:] == (152, 240, 3)
    assert len(dataset) == 2 and {"trans_lidar_to_cam", "trans_cam_to_img"} <= set(batch)
    # a frame without annotations: get_infos still works (one DontCare placeholder, no training box)
    empty = "99999"
    (dataset.root_split_path / "label_2" / f"{empty}.txt").write_text("")
    for sub, ext in (("velodyne", ".bin"), ("calib", ".txt"), ("image_2", ".jpg")):
        shutil.copy(dataset.root_split_path / sub / f"{fid}{ext}", dataset.root_split_path / sub / f"{empty}{ext}")
    (info_empty,) = dataset.get_infos(num_workers=1, sample_id_list=[empty])
    assert list(info_empty["annos"]["name"]) == ["DontCare"] and info_empty["annos"]["gt_boxes_lidar"].shape == (0, 7)


@pytest.mark.parametrize("name", ["mssf_second", "mssf_voxelnext"])
def test_training_steps_through_openpcdet(tools, name):
    torch.manual_seed(0)
    cfg = small(name, tools.ckpt)
    dataset, loader, model = build(cfg)
    assert model.module_list[0] is model.image_branch and model.image_branch.branch.frozen
    # the checkpoint's img_backbone.* weights were loaded into the frozen branch
    torch.testing.assert_close(model.image_branch.branch.backbone.conv1.weight, tools.branch.backbone.conv1.weight)
    seen = train(cfg, model, loader)
    assert len(seen) == len(loader) >= 2
    for loss, tb in seen:
        assert np.isfinite(loss) and tb["loss_mssf_seg"] > 0 and np.isfinite(tb["loss_mssf_seg"])
    fusion = [(n, p) for n, p in model.backbone_3d.named_parameters() if ".fusion." in n]
    assert len(fusion) > 10
    no_grad = [n for n, p in fusion if p.grad is None or not p.grad.abs().sum() > 0]
    assert not no_grad, no_grad
    assert all(p.grad is None for p in model.image_branch.parameters())  # frozen


def test_radar_only_twin_trains_without_images(tools):
    cfg = small("voxelnext_radar", tools.ckpt)
    dataset, loader, model = build(cfg)
    assert model.image_branch is None
    seen = train(cfg, model, loader)
    assert all(np.isfinite(loss) and "loss_mssf_seg" not in tb for loss, tb in seen)


def test_eval_one_epoch_and_vod_evaluation(tools, tmp_path):
    from eval_utils.eval_utils import eval_one_epoch

    cfg = small("mssf_voxelnext", tools.ckpt)
    cfg.MODEL.DENSE_HEAD.POST_PROCESSING.SCORE_THRESH = 0.0  # an untrained head: keep its boxes
    dataset, loader, model = build(cfg, training=False)
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, loader, epoch_id="0", logger=logging.getLogger("eval"), result_dir=tmp_path)
    for region in ("entire_area", "driving_corridor"):
        assert f"{region}/mAP3D_R40" in ret and f"{region}/Car_AP3D_R40" in ret
    assert "recall/roi_0.3" in ret
    dets = __import__("pickle").load(open(tmp_path / "result.pkl", "rb"))
    assert len(dets) == 2 and sum(len(d["name"]) for d in dets) > 0
    assert ret["entire_area/mAP3D_R40"] == pytest.approx(np.mean([ret[f"entire_area/{c}_AP3D_R40"] for c in cfg.CLASS_NAMES]))


def _kit_oracle():
    """tests/examples/evaluation/test_evaluation_vod_kit.py (the official VoD kit, loaded without its extras)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "examples" / "evaluation" / "test_evaluation_vod_kit.py"
    spec = importlib.util.spec_from_file_location("_vod_kit_oracle", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _line(a, k, score=None):
    l, h, w = a["dimensions"][k]
    vals = [a["alpha"][k], *a["bbox"][k], h, w, l, *a["location"][k], a["rotation_y"][k]]
    vals += [] if score is None else [score]
    head = [str(a["name"][k]), repr(float(a["truncated"][k])), str(int(a["occluded"][k]))]
    return " ".join(head + [repr(float(v)) for v in vals])


def test_vod_evaluation_equals_the_official_kit(tools, tmp_path):
    """dataset.evaluation() on OpenPCDet-style det_annos = the VoD kit on the same objects (within 0.01)."""
    pytest.importorskip("numba")
    oracle = _kit_oracle()
    dataset, _, _ = build(small("second_radar", tools.ckpt), training=False)
    rng = np.random.default_rng(0)
    gt_lines, det_lines, det_annos = [], [], []
    for info in dataset.kitti_infos:
        fid = info["point_cloud"]["lidar_idx"]
        gt_lines.append((dataset.root_split_path / "label_2" / f"{fid}.txt").read_text().splitlines())
        a = copy.deepcopy(info["annos"])
        n = len(a["name"])
        d = {k: np.asarray(a[k], dtype=np.float64) for k in ("truncated", "occluded", "alpha", "bbox", "dimensions",
                                                                 "location", "rotation_y")}
        d["location"] = d["location"] + rng.normal(0, 0.15, (n, 3))  # near misses and hits
        d["dimensions"] = d["dimensions"] * rng.uniform(0.85, 1.15, (n, 3))
        d["bbox"] = d["bbox"] + rng.normal(0, 3, (n, 4))
        d["name"] = np.where(rng.uniform(size=n) < 0.15, "Car", a["name"])  # some wrong classes
        d["score"] = rng.uniform(0.05, 1.0, n)
        d["frame_id"] = fid
        det_annos.append(d)
        det_lines.append([_line(d, k, d["score"][k]) for k in range(n)])  # kit_results undoes its +0.01 rad
    _, ours = dataset.evaluation(det_annos, ["Car", "Pedestrian", "Cyclist"])
    theirs = oracle.kit_results(gt_lines, det_lines, tmp_path)
    compared = 0
    for (region, cname, metric, rp), v in theirs.items():
        mine = ours[f"{region}/{cname}_AP{metric}_{rp}"]
        if np.isnan(mine):
            continue
        assert abs(mine - v) < 0.01, (region, cname, metric, rp, mine, v)
        compared += 1
    assert compared >= 8 and 0 < max(theirs.values()) < 100  # neither empty nor perfect


def overfit(cfg, fusion_key="BACKBONE_3D", epochs=6):
    """Train ``cfg`` on its few frames without augmentation (one-cycle to 3e-3) for ``epochs`` through OpenPCDet's
    ``train_one_epoch``; returns the mean loss of the first two and of the last two steps (the overfit tests of
    every detector kind: the last below 0.6 x the first for a model that learns)."""
    cfg.DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST = ["random_world_flip", "random_world_rotation", "random_world_scaling"]
    cfg.MODEL[fusion_key].AUG_ORDER = []
    cfg.OPTIMIZATION.update(LR=0.003, PCT_START=0.3)
    _, loader, model = build(cfg)
    seen = train(cfg, model, loader, epochs=epochs)
    return np.mean([loss for loss, _ in seen[:2]]), np.mean([loss for loss, _ in seen[-2:]])


def test_overfit_lowers_the_loss(tools):
    torch.manual_seed(0)
    first, last = overfit(small("mssf_second", tools.ckpt))
    assert last < 0.6 * first, (first, last)


def test_config_errors_name_the_key(tools):
    from mssf_examples.openpcdet.detectors import check_mssf_config
    from mssf_examples.openpcdet.vod_dataset import check_dataset_cfg

    cfg = small("mssf_second", tools.ckpt)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_3D.IMAGE_CHANNELS = [16, 16]
    with pytest.raises(MSSFError, match="MODEL.BACKBONE_3D.IMAGE_CHANNELS"):
        check_mssf_config(bad.MODEL, bad.DATA_CONFIG)
    bad = copy.deepcopy(cfg)
    bad.MODEL.IMAGE_BRANCH.FPN_CHANNELS = 32
    with pytest.raises(MSSFError, match="IMAGE_CHANNELS.*FPN_CHANNELS 32"):
        check_mssf_config(bad.MODEL, bad.DATA_CONFIG)
    bad = copy.deepcopy(cfg)
    bad.DATA_CONFIG.GET_ITEM_LIST = ["points"]
    with pytest.raises(MSSFError, match="DATA_CONFIG.GET_ITEM_LIST"):
        check_mssf_config(bad.MODEL, bad.DATA_CONFIG)
    bad = copy.deepcopy(cfg)
    bad.MODEL.BACKBONE_3D.AUG_ORDER = ["random_world_rotation", "random_world_flip", "random_world_scaling"]
    with pytest.raises(MSSFError, match="AUG_ORDER.*AUG_CONFIG_LIST"):
        check_mssf_config(bad.MODEL, bad.DATA_CONFIG)
    bad = copy.deepcopy(cfg)
    bad.DATA_CONFIG.POINT_FEATURE_ENCODING.src_feature_list = ["x", "y", "z", "intensity"]
    bad.DATA_CONFIG.POINT_FEATURE_ENCODING.used_feature_list = ["x", "y", "z", "intensity"]
    with pytest.raises(MSSFError, match="POINT_FEATURE_ENCODING.src_feature_list"):
        check_dataset_cfg(bad.DATA_CONFIG)
    bad = copy.deepcopy(cfg)
    bad.MODEL.IMAGE_BRANCH.CHECKPOINT = None
    with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH.CHECKPOINT"):
        build(bad)  # built through OpenPCDet's build_network: the detector raises


def test_documented_train_command_runs_openpcdet_train_py(tools, monkeypatch):
    """docs/frameworks.md's ``python -m mssf_examples.openpcdet train.py --cfg_file ...``, from tools/, with
    CPU sizes given through train.py's own options (``--epochs``, ``--workers``, ``--set``): OpenPCDet's
    train.py trains, saves a checkpoint and evaluates it (test.py's repeat_eval_ckpt) with evaluation()."""
    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.openpcdet.__main__ import main

    monkeypatch.setattr("time.sleep", lambda seconds: None)  # repeat_eval_ckpt waits 30 s for new checkpoints
    ckpt = tools.root.parent / "checkpoints" / "htc_r50_fpn_image_branch.pth"  # the config's CHECKPOINT
    ckpt.parent.mkdir(exist_ok=True)
    torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=256, num_outs=4).state_dict(), ckpt)
    cpu = ["--workers", "0", "--extra_tag", "cpu_test", "--batch_size", "2",
           "--set", "MODEL.IMAGE_BRANCH.DEPTH", "18", "MODEL.IMAGE_BRANCH.BASE_CHANNELS", "8",
           "OPTIMIZATION.PCT_START", "0.5"]
    cfg = ["--cfg_file", "cfgs/vod_models/mssf_voxelnext.yaml"]
    main(["--pure-torch-nms", "train.py", *cfg, "--epochs", "1", "--wo_gpu_stat", *cpu])
    out = tools.root.parent / "output" / "vod_models" / "mssf_voxelnext" / "cpu_test"
    assert (out / "ckpt" / "checkpoint_epoch_1.pth").is_file()
    log = "".join(p.read_text() for p in out.glob("*.log"))
    assert "VoD entire_area:" in log and "VoD driving_corridor:" in log, log[-2000:]
    # the documented evaluation of a checkpoint
    main(["--pure-torch-nms", "test.py", *cfg, "--ckpt", str(out / "ckpt" / "checkpoint_epoch_1.pth"), *cpu])
    logs = list((out / "eval").rglob("log_eval_*.txt"))
    assert logs and "VoD driving_corridor:" in logs[-1].read_text()


def test_image_branch_checkpoint_errors_name_the_key(tools, tmp_path):
    from mssf_examples.openpcdet.image_module import OpenPCDetImageBranch

    base = dict(DEPTH=18, BASE_CHANNELS=8, FPN_CHANNELS=16)
    with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH.CHECKPOINT: file not found"):
        OpenPCDetImageBranch({**base, "CHECKPOINT": str(tmp_path / "none.pth")})
    with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH.CHECKPOINT: .* does not fit"):
        OpenPCDetImageBranch({**base, "FPN_CHANNELS": 32, "CHECKPOINT": str(tools.ckpt)})  # 16-channel weights
    with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH: unknown keys \\['DEPHT'\\]"):
        OpenPCDetImageBranch({**base, "DEPHT": 50, "CHECKPOINT": str(tools.ckpt)})
    trainable = OpenPCDetImageBranch({**base, "FROZEN": False})  # from scratch: allowed, and trained
    assert all(p.requires_grad for p in trainable.parameters())
