"""``MSSFVoxelNeXtHead`` (MSSF-V's head in mmdetection3d) against its two references:

* OpenPCDet's own ``VoxelNeXtHead`` (the ``openpcdet`` fixture, commit 8caccce, run as released; ``KERNEL_SIZE_HEAD:
  3`` and ``USE_BIAS_BEFORE_NORM: True``, the authors' layout): its weights loaded into ours (``rot`` read as
  ``(cos, sin)`` there, ``(sin, cos)`` here), the forward on spconv in float32; its ``assign_targets``, ``get_loss``
  and ``decode_bbox_from_voxels_nuscenes`` in float64;
* the MSSF authors' ``VoxelNeXtHead`` (``EricLiuhhh/MSSF`` @ 8341012): ``get_targets_single``, ``FocalLossSparse`` /
  ``RegLossSparse`` and ``VoxelNeXtBBoxCoder.decode`` + ``get_task_detections`` (mmdet3d's own ``nms_bev``), written
  here in float64 with loops from their definitions.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import require_mmdet3d  # noqa: E402

F64 = torch.float64
PCR = [0.0, -25.6, -3.0, 51.2, 25.6, 2.0]
VOXEL = [0.4, 0.4, 0.125]  # stride 8 on 3.2 m cells: a 16 x 16 BEV (small grids keep the loops short)
NX = NY = 16
CLASSES = ["Car", "Pedestrian", "Cyclist"]
C = 16
CODE_WEIGHTS = [1.0, 0.5, 2.0, 1.0, 1.5, 1.0, 0.7, 1.2]


def _ours(loc_weight=0.25, code_weights=CODE_WEIGHTS, kernel_size=3, **test):
    require_mmdet3d()
    from mssf_examples.mmdet3d.voxelnext_head import MSSFVoxelNeXtHead

    return MSSFVoxelNeXtHead(C, 3, PCR, VOXEL, out_size_factor=8, head_channels=C, kernel_size=kernel_size,
                             loc_weight=loc_weight,
                             train_cfg=dict(code_weights=code_weights),
                             test_cfg=dict(dict(max_num=20, score_threshold=0.1, nms_thr=0.2, post_max_size=83,
                                                post_center_limit_range=PCR), **test))


def _scene(seed, batch=2, per_sample=60, boxes=5, grouped=False):
    """Random unique voxels (b, y, x) and boxes (centre z) with labels inside the grid; rows shuffled across
    samples unless ``grouped`` (OpenPCDet's and the authors' losses read the head's rows as sample-by-sample,
    spconv's order; ours does not need it)."""
    g = torch.Generator().manual_seed(seed)
    coords = []
    for b in range(batch):
        cells = torch.randperm(NY * NX, generator=g)[:per_sample]
        coords.append(torch.stack([torch.full_like(cells, b), cells // NX, cells % NX], 1))
    coords = torch.cat(coords)
    shuffled = torch.randperm(len(coords), generator=g)
    coords = coords[shuffled if not grouped else shuffled.sort().values].int()
    gts = []
    for _ in range(batch):
        xy = torch.rand(boxes, 2, generator=g, dtype=F64) * torch.tensor([50.0, 50.0], dtype=F64) + \
            torch.tensor([0.5, -25.0], dtype=F64)
        z = torch.rand(boxes, 1, generator=g, dtype=F64) - 1
        size = torch.rand(boxes, 3, generator=g, dtype=F64) * 4 + 0.5
        yaw = (torch.rand(boxes, 1, generator=g, dtype=F64) * 2 - 1) * math.pi
        # multiples of 1 / 64: exact in float32 (mmdet3d's boxes), centre z = bottom + h / 2 exact too
        box = torch.round(torch.cat([xy, z, size, yaw], 1) * 64) / 64
        gts.append((box, torch.randint(0, 3, (boxes,), generator=g)))
    return coords, gts


def _instances(gts):
    from mmdet3d.structures import LiDARInstance3DBoxes
    from mmengine.structures import InstanceData

    out = []
    for boxes, labels in gts:
        bottom = boxes.clone()
        bottom[:, 2] -= bottom[:, 5] / 2  # mmdet3d's boxes hold the bottom centre
        out.append(InstanceData(bboxes_3d=LiDARInstance3DBoxes(bottom), labels_3d=labels))
    return out


def _preds(coords, seed, dtype=F64):
    g = torch.Generator().manual_seed(seed)
    m = len(coords)
    return {"hm": torch.randn(m, 3, generator=g, dtype=dtype) * 2 - 2,
            "center": torch.rand(m, 2, generator=g, dtype=dtype) * 2 - 0.5,
            "center_z": torch.randn(m, 1, generator=g, dtype=dtype),
            "dim": torch.randn(m, 3, generator=g, dtype=dtype) * 0.5 + 0.5,
            "rot": torch.randn(m, 2, generator=g, dtype=dtype), "coords": coords, "batch_size": 2}


def _swap_rot(p):
    return {**p, "rot": p["rot"][:, [1, 0]]}


# ---------------------------------------------------------------------------------------------------
# OpenPCDet's VoxelNeXtHead
def _pcdet_head(kernel_size=3):
    import numpy as np
    from easydict import EasyDict
    from pcdet.models.dense_heads.voxelnext_head import VoxelNeXtHead

    head_dict = {n: {"out_channels": c, "num_conv": 2} for n, c in (("center", 2), ("center_z", 1), ("dim", 3),
                                                                     ("rot", 2))}
    cfg = EasyDict(dict(
        CLASS_NAMES_EACH_HEAD=[CLASSES], SHARED_CONV_CHANNEL=C, KERNEL_SIZE_HEAD=kernel_size, USE_BIAS_BEFORE_NORM=True,
        NUM_HM_CONV=2, SEPARATE_HEAD_CFG=dict(HEAD_ORDER=["center", "center_z", "dim", "rot"], HEAD_DICT=head_dict),
        TARGET_ASSIGNER_CONFIG=dict(FEATURE_MAP_STRIDE=8, NUM_MAX_OBJS=500, GAUSSIAN_OVERLAP=0.1, MIN_RADIUS=2),
        LOSS_CONFIG=dict(LOSS_WEIGHTS=dict(cls_weight=1.0, loc_weight=0.25, code_weights=CODE_WEIGHTS)),
        POST_PROCESSING=dict(SCORE_THRESH=0.1, POST_CENTER_LIMIT_RANGE=PCR, MAX_OBJ_PER_SAMPLE=20,
                             NMS_CONFIG=dict(NMS_TYPE="nms_gpu", NMS_THRESH=0.2, NMS_PRE_MAXSIZE=1000,
                                             NMS_POST_MAXSIZE=83))))
    grid = np.array([NX * 8, NY * 8, 40])
    head = VoxelNeXtHead(cfg, C, 3, CLASSES, grid, PCR, VOXEL)
    # its grid in float64 (it keeps float32 tensors; ours python floats): the float64 comparisons see one grid
    head.point_cloud_range = torch.tensor(PCR, dtype=F64)
    head.voxel_size = torch.tensor(VOXEL, dtype=F64)
    return head


@pytest.fixture
def pcdet_head(openpcdet, monkeypatch):
    monkeypatch.setattr(torch.Tensor, "cuda", lambda self, *a, **k: self)  # CPU only (as test_openpcdet_vod)
    return _pcdet_head




def _load_pcdet_weights(ours, pcdet_head):
    """OpenPCDet's SeparateHead tensors into ours: same names and layout; rot's 1x1 outputs swapped (spconv reads
    the (out, 1, 1, in) weight as (in, out))."""
    sd = {}
    for k, v in pcdet_head.heads_list[0].state_dict().items():
        if k.startswith("rot.1."):
            if k.endswith("weight"):
                v = v.reshape(v.shape[3], v.shape[0])[:, [1, 0]].reshape(v.shape)
            else:
                v = v[[1, 0]]
        sd[f"net.heads.{k}"] = v
    ours.load_state_dict(sd, strict=True)


@pytest.mark.parametrize("kernel_size", [3, 1])  # 3: VoxelNeXt's and the authors'; 1: this project's OpenPCDet yaml
def test_forward_equals_openpcdet_voxelnext_head(pcdet_head, kernel_size):
    import spconv.pytorch as spconv

    ours = _ours(kernel_size=kernel_size)
    pcdet_head = pcdet_head(kernel_size)
    _load_pcdet_weights(ours, pcdet_head)
    coords, _ = _scene(1)
    feats = torch.randn(len(coords), C, generator=torch.Generator().manual_seed(2))
    x = spconv.SparseConvTensor(feats, coords, [NY, NX], 2)
    pcdet_head.train(), ours.train()  # (train: spconv's CPU kernels refuse biased convolutions in eval mode)
    theirs = pcdet_head.heads_list[0](x)
    mine = ours([x], 2)
    for name in ("hm", "center", "center_z", "dim"):
        torch.testing.assert_close(mine[name], theirs[name], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(mine["rot"], theirs["rot"][:, [1, 0]], rtol=1e-4, atol=1e-4)


def _pcdet_targets(pcdet_head, coords, gts):
    batch = len(gts)
    g = max(len(b) for b, _ in gts)
    gt = torch.zeros(batch, g, 8, dtype=F64)
    for i, (boxes, labels) in enumerate(gts):
        gt[i, :len(boxes), :7] = boxes
        gt[i, :len(boxes), 7] = labels.to(F64) + 1
    spatial = [coords[coords[:, 0] == b][:, [2, 1]].to(F64) for b in range(batch)]
    num = [torch.tensor(len(s)) for s in spatial]
    return pcdet_head.assign_targets(gt, num, spatial, [NY, NX])


def test_targets_and_loss_equal_openpcdet_in_float64(pcdet_head):
    pcdet_head = pcdet_head()
    ours = _ours(code_weights=CODE_WEIGHTS[:6] + CODE_WEIGHTS[6:][::-1])  # ours weigh (sin, cos), OpenPCDet (cos, sin)
    coords, gts = _scene(3, grouped=True)
    t = _pcdet_targets(pcdet_head, coords, gts)
    preds = _preds(coords, 4)
    heatmap, rows, targets = ours.targets(preds, _instances(gts))
    order = torch.cat([torch.nonzero(coords[:, 0] == b).flatten() for b in range(2)])  # theirs: sample by sample
    torch.testing.assert_close(heatmap[order], t["heatmaps"][0], rtol=0, atol=1e-12)
    assert float(t["heatmaps"][0].max()) == 1.0
    for b in range(2):
        sample_rows = torch.nonzero(coords[:, 0] == b).flatten()
        mask = t["masks"][0][b].bool()
        assert int(mask.sum()) == len(rows[b]) == 5
        assert torch.equal(sample_rows[t["inds"][0][b][mask]], rows[b])
        want = t["target_boxes"][0][b][mask]
        torch.testing.assert_close(targets[b], want[:, [0, 1, 2, 3, 4, 5, 7, 6]], rtol=0, atol=1e-12)
    # their get_loss on the same float64 predictions (batch_index: rows in the spconv tensor's order)
    theirs = {k: v.clone() for k, v in _swap_rot(preds).items() if k not in ("coords", "batch_size")}
    pcdet_head.forward_ret_dict = {"pred_dicts": [theirs], "target_dicts": t, "batch_index": coords[:, 0].long(),
                                   "voxel_indices": coords.long()}
    loss, tb = pcdet_head.get_loss()
    mine = ours.loss_by_feat(preds, _instances(gts))
    assert mine["loss_heatmap"].item() == pytest.approx(tb["hm_loss_head_0"], rel=1e-12)
    # (rel 1e-7: the head keeps its code weights in a float32 buffer, 0.7 and 1.2 are rounded there)
    assert mine["loss_bbox"].item() == pytest.approx(tb["loc_loss_head_0"], rel=1e-7)
    assert float(mine["loss_heatmap"] + mine["loss_bbox"]) == pytest.approx(float(loss), rel=1e-7)


def test_decoded_boxes_equal_openpcdet_in_float64(pcdet_head):
    pcdet_head = pcdet_head()
    from pcdet.models.model_utils.centernet_utils import decode_bbox_from_voxels_nuscenes

    ours = _ours()
    coords, _ = _scene(5)
    preds = _preds(coords, 6)
    theirs_in = _swap_rot(preds)
    theirs = decode_bbox_from_voxels_nuscenes(
        batch_size=2, indices=coords.long(), obj=torch.sigmoid(theirs_in["hm"]), rot_cos=theirs_in["rot"][:, :1],
        rot_sin=theirs_in["rot"][:, 1:], center=theirs_in["center"], center_z=theirs_in["center_z"],
        dim=theirs_in["dim"].exp(), point_cloud_range=torch.tensor(PCR, dtype=F64),
        voxel_size=torch.tensor(VOXEL, dtype=F64), feature_map_stride=8, K=20, score_thresh=0.1,
        post_center_limit_range=torch.tensor(PCR, dtype=F64))
    mine = ours.net.decode(preds, 0.1, None, 1000, class_agnostic_nms=True, center_range=PCR)
    for b in range(2):
        order = torch.sort(theirs[b]["pred_scores"], descending=True, stable=True).indices
        assert len(order) > 3
        torch.testing.assert_close(mine[b]["scores"], theirs[b]["pred_scores"][order], rtol=0, atol=1e-12)
        assert mine[b]["labels"].tolist() == theirs[b]["pred_labels"][order].tolist()
        torch.testing.assert_close(mine[b]["boxes"], theirs[b]["pred_boxes"][order], rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------------------------------
# The authors' VoxelNeXtHead (their definitions, float64 loops)
def their_gaussian_radius(height, width, min_overlap):
    """mmdet3d's gaussian_radius (their import), as written there."""
    a1, b1, c1 = 1, height + width, width * height * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1 ** 2 - 4 * a1 * c1)) / 2
    a2, b2, c2 = 4, 2 * (height + width), (1 - min_overlap) * width * height
    r2 = (b2 + math.sqrt(b2 ** 2 - 4 * a2 * c2)) / 2
    a3, b3, c3 = 4 * min_overlap, -2 * min_overlap * (height + width), (min_overlap - 1) * width * height
    r3 = (b3 + math.sqrt(b3 ** 2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def their_targets(boxes, labels, spatial):
    """get_targets_single of one sample (one task): heatmap (K, n), anno_box (G, 8) (sin, cos), ind, mask."""
    n = len(spatial)
    heat = torch.zeros(3, n, dtype=F64)
    anno, ind, mask = torch.zeros(len(boxes), 8, dtype=F64), torch.zeros(len(boxes), dtype=torch.long), []
    for k in range(len(boxes)):
        x, y, z, dx, dy, dz, rot = boxes[k].tolist()
        length, width = dx / VOXEL[0] / 8, dy / VOXEL[1] / 8
        radius = max(2, int(their_gaussian_radius(width, length, 0.1)))
        cx, cy = (x - PCR[0]) / VOXEL[0] / 8, (y - PCR[1]) / VOXEL[1] / 8
        if not (0 <= int(cx) < NX and 0 <= int(cy) < NY):
            mask.append(0)
            continue
        sigma = (2 * radius + 1) / 6
        dist = [(float(sx) - cx) ** 2 + (float(sy) - cy) ** 2 for sx, sy in spatial.tolist()]
        ind[k] = min(range(n), key=lambda i: dist[i])
        near = [(float(sx) - float(spatial[ind[k], 0])) ** 2 + (float(sy) - float(spatial[ind[k], 1])) ** 2
                for sx, sy in spatial.tolist()]
        for i in range(n):
            for d in (dist[i], near[i]):
                heat[labels[k], i] = max(float(heat[labels[k], i]), math.exp(-d / (2 * sigma * sigma)))
        anno[k] = torch.tensor([cx - float(spatial[ind[k], 0]), cy - float(spatial[ind[k], 1]), z, math.log(dx),
                                math.log(dy), math.log(dz), math.sin(rot), math.cos(rot)], dtype=F64)
        mask.append(1)
    return heat, anno, ind, torch.tensor(mask)


def their_losses(preds, coords, gts):
    """clip_sigmoid + FocalLossSparse over the batch; RegLossSparse summed (their weights: 1)."""
    order = [torch.nonzero(coords[:, 0] == b).flatten() for b in range(2)]
    heats, reg_pred, reg_target, masks = [], [], [], []
    codes = torch.cat([preds["center"], preds["center_z"], preds["dim"], preds["rot"]], 1)
    for b, (boxes, labels) in enumerate(gts):
        heat, anno, ind, mask = their_targets(boxes, labels, coords[order[b]][:, [2, 1]])
        heats.append(heat)
        reg_pred.append(codes[order[b]][ind])
        reg_target.append(anno)
        masks.append(mask)
    gt = torch.cat(heats, 1).T
    pred = torch.sigmoid(preds["hm"][torch.cat(order)]).clamp(1e-4, 1 - 1e-4)
    pos = gt.eq(1).to(F64)
    pos_loss = (torch.log(pred) * (1 - pred) ** 2 * pos).sum()
    neg_loss = (torch.log(1 - pred) * pred ** 2 * (1 - gt) ** 4 * gt.lt(1).to(F64)).sum()
    num_pos = pos.sum()
    heat_loss = -neg_loss if num_pos == 0 else -(pos_loss + neg_loss) / num_pos
    mask = torch.stack(masks).to(F64)
    num = mask.sum()
    l1 = (torch.stack(reg_pred) * mask[..., None] - torch.stack(reg_target) * mask[..., None]).abs()
    bbox_loss = (l1.sum(dim=(0, 1)) / torch.clamp_min(num, 1.0)).sum()
    return heat_loss, bbox_loss


def test_loss_equals_the_authors_head_in_float64():
    ours = _ours(loc_weight=1.0, code_weights=[1.0] * 8)  # their weights
    coords, gts = _scene(7, boxes=4)
    preds = _preds(coords, 8)
    want_heat, want_bbox = their_losses(preds, coords, gts)
    mine = ours.loss_by_feat(preds, _instances(gts))
    assert mine["loss_heatmap"].item() == pytest.approx(float(want_heat), rel=1e-12)
    assert mine["loss_bbox"].item() == pytest.approx(float(want_bbox), rel=1e-12)


def test_predictions_equal_the_authors_coder_and_nms_in_float64():
    """VoxelNeXtBBoxCoder.decode (top max_num (voxel, class) scores, score > thr, centre in range), then
    get_task_detections' nms_bev (mmdet3d's) and the z - h / 2 of predict_by_feat, into LiDARInstance3DBoxes."""
    require_mmdet3d()  # before mmdet3d.models (mmcv's compiled ops): skips where they are absent, fails under CI
    from mmdet3d.models.layers import nms_bev
    from mmdet3d.structures import LiDARInstance3DBoxes, xywhr2xyxyr

    ours = _ours(score_threshold=0.02, nms_thr=0.2, post_max_size=6)
    coords, _ = _scene(9)
    preds = _preds(coords, 10)
    metas = [dict(box_type_3d=LiDARInstance3DBoxes)] * 2
    results = ours.predict_by_feat(preds, metas)
    for b in range(2):
        rows = torch.nonzero(coords[:, 0] == b).flatten()
        heat = torch.sigmoid(preds["hm"][rows])
        scores, idx = heat.flatten().topk(20)
        voxel, labels = idx // 3, idx % 3
        boxes = []
        for v in voxel.tolist():
            _, y, x = coords[rows[v]].tolist()
            r = rows[v]
            dims = torch.exp(preds["dim"][r])
            boxes.append(torch.stack([(x + preds["center"][r, 0]) * 8 * VOXEL[0] + PCR[0],
                                      (y + preds["center"][r, 1]) * 8 * VOXEL[1] + PCR[1], preds["center_z"][r, 0],
                                      *dims, torch.atan2(preds["rot"][r, 0], preds["rot"][r, 1])]))
        boxes = torch.stack(boxes)
        rng = torch.tensor(PCR, dtype=F64)
        keep = (scores > 0.02) & (boxes[:, :3] >= rng[:3]).all(1) & (boxes[:, :3] <= rng[3:]).all(1)
        boxes, scores, labels = boxes[keep], scores[keep], labels[keep]
        # (mmdet3d boxes are float32, and mmcv's nms_rotated wants the scores in the same type)
        sel = nms_bev(xywhr2xyxyr(LiDARInstance3DBoxes(boxes).bev), scores.float(), 0.2, pre_max_size=1000,
                      post_max_size=6)
        want = boxes[sel].clone()
        want[:, 2] -= want[:, 5] / 2
        res = results[b]
        assert isinstance(res.bboxes_3d, LiDARInstance3DBoxes) and len(res.bboxes_3d) == len(sel) > 0
        # (mmdet3d's boxes hold float32: the float64 decoding rounded once)
        torch.testing.assert_close(res.bboxes_3d.tensor, want.float(), rtol=0, atol=1e-5)
        torch.testing.assert_close(res.scores_3d, scores[sel], rtol=0, atol=1e-12)
        assert res.labels_3d.tolist() == labels[sel].tolist()


def test_settings_and_inputs_are_checked():
    from mssf_examples.mmdet3d.voxelnext_head import MSSFVoxelNeXtHead, bev_grid

    from mssf_blocks.errors import MSSFError

    with pytest.raises(MSSFError, match="test_cfg: unknown keys \\['nms_type'\\]"):
        _ours(nms_type="rotate")
    with pytest.raises(MSSFError, match="train_cfg: unknown keys"):
        MSSFVoxelNeXtHead(C, 3, PCR, VOXEL, train_cfg=dict(dense_reg=1))
    with pytest.raises(MSSFError, match="feats: expected \\[SparseConvTensor\\]"):
        _ours()(torch.zeros(3, C))
    # the BEV of the TJ4D voxel grid (1408 x 1600 voxels at stride 8): 176 x 200 cells of 0.4 m
    grid = bev_grid([0, -40, -4, 70.4, 40, 2], [0.05, 0.05, 0.125], 8)
    assert (grid.nx, grid.ny) == (176, 200) and grid.cell_x == pytest.approx(0.4) and grid.cell_y == pytest.approx(0.4)
