"""The converted MSSF-PP head against the real mmdet3d 1.4 ``Anchor3DHead`` built from the authors' config.

Their ``bbox_head`` dict (``pointpillars_hv_secfpn_vod_mm_backbone``, EricLiuhhh/MSSF @ 8341012) builds
mmdet3d's head; random tensors in their key layout load into it and, through
``mssf_examples.models.authors_checkpoint.head_pairs``, into the examples' ``AnchorHead`` built as theirs. Their
``_predict_by_feat_single`` runs as released with ``box3d_multiclass_nms`` replaced by a pass-through of
every (anchor, class) pair, so everything but the NMS is theirs: flattening, anchor generator, box coder,
direction fix. (mmdet3d generates its anchors in float32: the boxes agree to float32 rounding.)
"""

from __future__ import annotations

import math
import os
from types import SimpleNamespace

import pytest
import torch

pytest.importorskip("spconv")

F64 = torch.float64
OURS = ("Car", "Pedestrian", "Cyclist")
THEIRS = ("Pedestrian", "Cyclist", "Car")

HEAD_CFG = dict(
    type="Anchor3DHead", num_classes=3, in_channels=384, feat_channels=384, use_direction_classifier=True,
    assign_per_class=True,
    anchor_generator=dict(type="AlignedAnchor3DRangeGenerator",
                          ranges=[[0, -25.6, -0.6, 51.2, 25.6, -0.6], [0, -25.6, -0.6, 51.2, 25.6, -0.6],
                                  [0, -25.6, -1.78, 51.2, 25.6, -1.78]],
                          sizes=[[0.8, 0.6, 1.73], [1.76, 0.6, 1.73], [3.9, 1.6, 1.56]], rotations=[0, 1.57],
                          reshape_out=False),
    diff_rad_by_sin=True, bbox_coder=dict(type="DeltaXYZWLHRBBoxCoder"),
    loss_cls=dict(type="mmdet.FocalLoss", use_sigmoid=True, gamma=2.0, alpha=0.25, loss_weight=1.0),
    loss_bbox=dict(type="mmdet.SmoothL1Loss", beta=1.0 / 9.0, loss_weight=2.0),
    loss_dir=dict(type="mmdet.CrossEntropyLoss", use_sigmoid=False, loss_weight=0.2))


def _mmdet3d():
    try:
        from mmdet3d.registry import MODELS
        from mmdet3d.structures import LiDARInstance3DBoxes
        from mmdet3d.utils import register_all_modules
        import mmdet3d.models.dense_heads.base_3d_dense_head as base
    except Exception as exc:  # noqa: BLE001 - absent, or mmcv without its compiled ops
        if os.environ.get("CI") == "true":
            pytest.fail(f"CI=true: the real mmdet3d 1.4 is needed ({exc})")
        pytest.skip(f"needs the real mmdet3d 1.4 with mmcv's compiled ops ({exc})")
    register_all_modules(init_default_scope=False)
    return MODELS, LiDARInstance3DBoxes, base


def test_converted_anchor_head_equals_mmdet3d_anchor3d_head(monkeypatch):
    from mssf_examples.models.authors_checkpoint import head_pairs
    from mssf_examples.models.heads import AnchorHead, BEVGrid
    from mssf_examples.models.heads.authors import authors_anchor_head_kwargs, authors_anchor_z_centers
    from mssf_examples.models.presets import VOD

    models, boxes_cls, base = _mmdet3d()
    theirs_head = models.build(dict(HEAD_CFG)).double().eval()
    g = torch.Generator().manual_seed(0)
    sd = {k: 0.05 * torch.randn(v.shape, generator=g, dtype=F64) for k, v in theirs_head.state_dict().items()}
    theirs_head.load_state_dict(sd, strict=True)
    ny, nx = 6, 5
    sizes = VOD.anchor_sizes
    ours = AnchorHead(384, BEVGrid(0.0, -25.6, 51.2, 25.6, ny, nx), sizes,
                      authors_anchor_z_centers(OURS, sizes, "vod"), dtype=F64, **authors_anchor_head_kwargs()).eval()
    ckpt = {f"bbox_head.{k}": v for k, v in sd.items()}  # their detector's names
    pairs = head_pairs(ckpt, SimpleNamespace(preset=SimpleNamespace(class_names=OURS), head=ours), "mssf_pp")
    ours.load_state_dict({o[len("head."):]: ckpt[k] if fn is None else fn(ckpt[k]) for k, (o, fn) in pairs.items()},
                         strict=True)

    def every_pair(bboxes, bboxes_for_nms, scores, score_thr, max_num, cfg, dir_scores):
        n, k = scores.shape[0], scores.shape[1] - 1  # (their dummy background column last)
        return (bboxes.repeat_interleave(k, 0), scores[:, :k].reshape(-1),
                torch.arange(k).repeat(n), dir_scores.repeat_interleave(k, 0))

    monkeypatch.setattr(base, "box3d_multiclass_nms", every_pair)
    x = torch.randn(1, 384, ny, nx, generator=g, dtype=F64)
    with torch.no_grad():
        cls, reg, dirs = theirs_head.forward_single(x)
        anchors = theirs_head.prior_generator.grid_anchors([(ny, nx)], device="cpu")[0].reshape(-1, 7)
        res = theirs_head._predict_by_feat_single([cls[0]], [reg[0]], [dirs[0]], [anchors],
                                                  {"box_type_3d": boxes_cls},
                                                  cfg=SimpleNamespace(get=lambda k, d=None: {"nms_pre": -1}.get(k, d),
                                                                      max_num=10**6))
        preds = ours(x)
        boxes = ours.decode_boxes(preds)[0]
        scores = torch.sigmoid(preds["cls"][0])
    their_boxes = res.bboxes_3d.tensor.reshape(ny * nx, 6, 3, 7)[:, :, 0]  # (cell, their anchor, 7)
    their_scores = res.scores_3d.reshape(ny * nx, 6, 3)
    perm = [THEIRS.index(c) for c in OURS]
    ours_boxes, ours_scores = boxes.reshape(ny * nx, 3, 2, 7), scores.reshape(ny * nx, 3, 2, 3)
    for k in range(3):
        for r in range(2):
            a = perm[k] * 2 + r
            assert (ours_scores[:, k, r] - their_scores[:, a][:, perm]).abs().max() <= 1e-12
            want = their_boxes[:, a].clone()
            want[:, 2] += want[:, 5] / 2  # their bottom z, our centre z
            assert (ours_boxes[:, k, r, :6] - want[:, :6]).abs().max() <= 1e-5
            dyaw = torch.remainder(ours_boxes[:, k, r, 6] - want[:, 6] + math.pi, 2 * math.pi) - math.pi
            assert dyaw.abs().max() <= 1e-5
