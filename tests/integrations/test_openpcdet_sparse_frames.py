"""Radar frames with no (or few) voxels through OpenPCDet's own code (the ``openpcdet`` fixture).

VoD has frames without any radar return in the field of view at range. A generated VoD tree whose first
train and first val frame have an empty ``.bin`` (0 points) runs through ``build_dataloader``,
``build_network``, ``train_one_epoch`` and ``eval_one_epoch``. Stock ``VoxelNeXtHead`` (OpenPCDet
8caccce) dies there (``IndexError: argmin()`` in training, ``RuntimeError: stack expects each tensor to
be equal size`` in evaluation) and labels every detection of a frame with fewer voxels than
``MAX_OBJ_PER_SAMPLE`` with the first class; a batch of only empty frames stops the backbone.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
from test_openpcdet_vod import CONFIGS, train  # noqa: E402
from test_openpcdet_vod import small as _small  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
DATA = "../data/vod_sparse/radar_5frames"  # beside test_openpcdet_vod's tree, from tools/


@pytest.fixture(scope="module")
def tools(openpcdet, tmp_path_factory):
    """tools/ as cwd, a tree whose first train and first val frames have no point; classes registered."""
    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import generate_scene, scene_seed

    tools = openpcdet / "tools"
    shutil.copytree(CONFIGS / "dataset_configs", tools / "cfgs" / "dataset_configs", dirs_exist_ok=True)
    shutil.copytree(CONFIGS / "vod_models", tools / "cfgs" / "vod_models", dirs_exist_ok=True)
    splits = {s: [generate_scene(scene_seed(3, s, i)) for i in range(2)] for s in ("train", "val")}
    ids = write_vod_tree(openpcdet / "data" / "vod_sparse", splits, sensor="radar_5frames", image_format="jpg")
    velodyne = openpcdet / "data" / "vod_sparse" / "radar_5frames" / "training" / "velodyne"
    for fid in (ids["train"][0], ids["val"][0]):
        (velodyne / f"{fid}.bin").write_bytes(b"")  # no radar return at all
    cwd, cuda = os.getcwd(), torch.Tensor.cuda
    os.chdir(tools)
    torch.Tensor.cuda = lambda self, *args, **kwargs: self  # CPU only (as test_openpcdet_vod)
    try:
        from mssf_examples.openpcdet import register
        from mssf_examples.openpcdet.__main__ import main

        register(pure_torch_box_ops=True)
        main(["create_vod_infos", "cfgs/dataset_configs/vod_radar5_dataset.yaml", "--data_path", DATA, "--workers", "1"])
        torch.manual_seed(0)
        ckpt = tmp_path_factory.mktemp("ckpt") / "image_branch.pth"
        torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=16, num_outs=4).state_dict(), ckpt)
        yield types.SimpleNamespace(root=tools, ckpt=ckpt, empty=(ids["train"][0], ids["val"][0]))
    finally:
        torch.Tensor.cuda = cuda
        os.chdir(cwd)


def small(name, ckpt, still=False):
    cfg = _small(name, ckpt)
    cfg.DATA_CONFIG.DATA_PATH = DATA
    if still:  # no random augmentation, no shuffling: two builds see the same points
        cfg.DATA_CONFIG.DATA_AUGMENTOR.DISABLE_AUG_LIST = [a.NAME for a in cfg.DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST]
        cfg.MODEL.BACKBONE_3D.AUG_ORDER = []
        cfg.DATA_CONFIG.DATA_PROCESSOR[1].SHUFFLE_ENABLED = {"train": False, "test": False}
    return cfg


def build(cfg, training=True, batch_size=2):
    from pcdet.datasets import build_dataloader
    from pcdet.models import build_network

    dataset, loader, _ = build_dataloader(cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=batch_size, dist=False,
                                          workers=0, training=training, seed=0)
    return dataset, loader, build_network(cfg.MODEL, num_class=len(cfg.CLASS_NAMES), dataset=dataset)


def batch_of(dataset, frames):
    """OpenPCDet's collate_batch + load_data_to_gpu of the dataset items of these frame ids."""
    from pcdet.models import load_data_to_gpu

    index = {str(info["point_cloud"]["lidar_idx"]): i for i, info in enumerate(dataset.kitti_infos)}
    batch = dataset.collate_batch([dataset[index[f]] for f in frames])
    load_data_to_gpu(batch)
    return batch


@pytest.mark.parametrize("name", ["mssf_voxelnext", "voxelnext_radar"])
def test_batch_with_an_empty_frame_trains_with_the_normal_frames_loss(tools, name):
    """[empty, normal] trains, and its loss is the loss of [normal] alone: the empty frame adds nothing."""
    cfg = small(name, tools.ckpt, still=True)
    dataset, loader, model = build(cfg)
    empty = tools.empty[0]
    normal = [str(i["point_cloud"]["lidar_idx"]) for i in dataset.kitti_infos if i["point_cloud"]["lidar_idx"] != empty]
    assert len(dataset.get_lidar(empty)) == 0 and len(normal) == 1
    model.train()
    with pytest.warns(UserWarning, match=r"1 frame\(s\) of a training batch have no voxel.*get no target"):
        ret, tb, _ = model(batch_of(dataset, [empty] + normal))
    assert tb["frames_without_voxels"] == 1 and np.isfinite(float(ret["loss"]))
    ret["loss"].backward()
    grads = {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}
    assert grads and all(torch.isfinite(g).all() for g in grads.values())
    model.zero_grad()
    ret_alone, tb_alone, _ = model(batch_of(dataset, normal))
    assert tb_alone["frames_without_voxels"] == 0
    torch.testing.assert_close(ret["loss"], ret_alone["loss"], rtol=1e-5, atol=1e-6)
    for key in ("hm_loss_head_0", "loc_loss_head_0"):
        assert tb[key] == pytest.approx(tb_alone[key], rel=1e-5)
    # and OpenPCDet's train_one_epoch over the split (both frames in one batch) runs
    seen = train(cfg, model, loader)
    assert len(seen) == 1 and np.isfinite(seen[0][0]) and seen[0][1]["frames_without_voxels"] == 1


def test_eval_one_epoch_with_an_empty_frame(tools, tmp_path):
    from eval_utils.eval_utils import eval_one_epoch

    cfg = small("mssf_voxelnext", tools.ckpt)
    cfg.MODEL.DENSE_HEAD.POST_PROCESSING.SCORE_THRESH = 0.0  # an untrained head: keep its boxes
    dataset, loader, model = build(cfg, training=False)
    args = types.SimpleNamespace(save_to_file=False, infer_time=False)
    ret = eval_one_epoch(cfg, args, model, loader, epoch_id="0", logger=logging.getLogger("eval"), result_dir=tmp_path)
    assert "entire_area/mAP3D_R40" in ret
    dets = {d["frame_id"]: d for d in __import__("pickle").load(open(tmp_path / "result.pkl", "rb"))}
    assert len(dets[tools.empty[1]]["name"]) == 0
    assert sum(len(d["name"]) for d in dets.values()) > 0


@pytest.mark.parametrize("name", ["mssf_voxelnext", "mssf_second"])
def test_a_batch_of_one_empty_frame_is_skipped_in_training_and_empty_in_evaluation(tools, name):
    cfg = small(name, tools.ckpt, still=True)
    dataset, _, model = build(cfg)
    model.train()
    with pytest.warns(UserWarning, match="without any voxel .* is skipped"):
        ret, tb, _ = model(batch_of(dataset, [tools.empty[0]]))
    assert float(ret["loss"]) == 0.0 and tb["batches_without_voxels"] == 1
    ret["loss"].backward()
    assert all(p.grad is None for p in model.parameters())  # the optimizer steps over no weight
    model.eval()
    with torch.no_grad():
        preds, recall = model(batch_of(dataset, [tools.empty[0]]))
    assert len(preds) == 1 and preds[0]["pred_boxes"].shape == (0, 7) and len(preds[0]["pred_labels"]) == 0
    assert recall["gt"] > 0 and recall["rcnn_0.3"] == 0  # its boxes still count, none found


def test_frame_with_fewer_voxels_than_max_obj_gets_its_own_class_labels(tools):
    """MAX_OBJ_PER_SAMPLE (the shipped 500) above the frame's voxels: every detection keeps the class whose
    heat-map score it is (stock: index // K labels them all with the first class)."""
    cfg = small("voxelnext_radar", tools.ckpt)
    cfg.MODEL.DENSE_HEAD.POST_PROCESSING.update(MAX_OBJ_PER_SAMPLE=500, SCORE_THRESH=0.0)
    cfg.MODEL.DENSE_HEAD.POST_PROCESSING.NMS_CONFIG.NMS_THRESH = 1.0  # keep every box: scores stay comparable
    dataset, _, model = build(cfg, training=False, batch_size=1)
    torch.manual_seed(1)
    with torch.no_grad():
        for p in model.dense_head.heads_list[0].hm[-1].parameters():
            p.normal_(0, 1.0)  # heat-map scores that differ between the classes
    model.eval()
    normal = [str(i["point_cloud"]["lidar_idx"]) for i in dataset.kitti_infos if i["point_cloud"]["lidar_idx"] != tools.empty[1]]
    batch = batch_of(dataset, normal)
    with torch.no_grad():
        preds, _ = model(batch)
    hm = model.dense_head.forward_ret_dict["pred_dicts"][0]["hm"].sigmoid()  # (voxels, classes)
    assert 0 < hm.shape[0] < 500
    scores, labels = preds[0]["pred_scores"], preds[0]["pred_labels"]
    assert len(scores) > 0
    for s, lab in zip(scores.tolist(), labels.tolist()):
        assert torch.isclose(hm[:, lab - 1], torch.tensor(s), rtol=0, atol=1e-6).any(), (s, lab)


def test_per_frame_decoding_equals_the_stock_batched_decoding(tools):
    """Where the stock head can decode (every frame with at least K voxels), decoding each frame alone (the
    path taken for short frames) gives the same labels, and boxes and scores up to float32 rounding."""
    from pcdet.models.dense_heads.voxelnext_head import VoxelNeXtHead

    cfg = small("voxelnext_radar", tools.ckpt)
    cfg.MODEL.DENSE_HEAD.POST_PROCESSING.update(MAX_OBJ_PER_SAMPLE=20, SCORE_THRESH=0.0)
    dataset, _, model = build(cfg, training=False)
    model.eval()
    normal = [str(i["point_cloud"]["lidar_idx"]) for i in dataset.kitti_infos if i["point_cloud"]["lidar_idx"] != tools.empty[1]]
    with torch.no_grad():
        model(batch_of(dataset, normal * 2))  # the same frame twice: a batch of two full frames
    head = model.dense_head
    preds, indices = head.forward_ret_dict["pred_dicts"], head.forward_ret_dict["voxel_indices"]
    shape = model.backbone_3d.sparse_shape[1:] if hasattr(model.backbone_3d, "sparse_shape") else None
    stock = VoxelNeXtHead.generate_predicted_boxes(head, 2, [dict(p) for p in preds], indices, shape)
    assert all(len(s["pred_scores"]) > 0 for s in stock)
    for b in range(2):
        rows = indices[:, 0] == b
        frame_indices = indices[rows].clone()
        frame_indices[:, 0] = 0
        alone = head._decode_with_k(20, [{k: v[rows] for k, v in p.items()} for p in preds], frame_indices, shape)
        torch.testing.assert_close(alone["pred_labels"], stock[b]["pred_labels"], rtol=0, atol=0)
        # float32 rounding only: vectorised atan2 / sigmoid over another tensor length (measured: 2.4e-7 rad)
        torch.testing.assert_close(alone["pred_scores"], stock[b]["pred_scores"], rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(alone["pred_boxes"], stock[b]["pred_boxes"], rtol=1e-6, atol=1e-6)
