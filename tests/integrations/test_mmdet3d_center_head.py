"""``CenterHeadWithoutVelocity`` against mmdet3d 1.4's own ``CenterHead`` on the velocity path it was written for.

The reference is mmdet3d's unmodified ``CenterHead`` with a ``vel`` branch, given the same boxes with zero velocity
(9 values) and code weights 0 on the two velocity columns, its shared and per-task layers copied from ours: the
heatmap and box losses of every task agree, and so do the decoded boxes (their first 7 values), scores and labels.
The head's settings are those of ``_base_/models/mssf_centerpoint_vod.py`` on a small grid. Stock ``CenterHead``
itself cannot take 7-value boxes (what the subclass is for).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import require_mmdet3d  # noqa: E402

RANGE = [0, -25.6, -3, 51.2, 25.6, 2]
VOXEL = [0.4, 0.4, 0.125]  # 128 x 128 cells, 16 x 16 feature map at out_size_factor 8
TASKS = [dict(num_class=1, class_names=["Car"]), dict(num_class=1, class_names=["Pedestrian"]),
         dict(num_class=1, class_names=["Cyclist"])]


def head_cfg(kind, velocity):
    heads = dict(reg=(2, 2), height=(1, 2), dim=(3, 2), rot=(2, 2))
    if velocity:
        heads["vel"] = (2, 2)
    weights = [1.0] * 8 + ([0.0, 0.0] if velocity else [])
    return dict(
        type=kind, in_channels=32, tasks=TASKS, common_heads=heads, share_conv_channel=16,
        bbox_coder=dict(type="CenterPointBBoxCoder", pc_range=RANGE[:2], post_center_range=RANGE, max_num=100,
                        score_threshold=0.0, out_size_factor=8, voxel_size=VOXEL[:2], code_size=9 if velocity else 7),
        separate_head=dict(type="SeparateHead", init_bias=-2.19, final_kernel=3),
        loss_cls=dict(type="mmdet.GaussianFocalLoss", reduction="mean"),
        loss_bbox=dict(type="mmdet.L1Loss", reduction="mean", loss_weight=0.25), norm_bbox=True,
        train_cfg=dict(grid_size=[128, 128, 40], voxel_size=VOXEL, point_cloud_range=RANGE, out_size_factor=8,
                       dense_reg=1, gaussian_overlap=0.1, max_objs=50, min_radius=2, code_weights=weights),
        test_cfg=dict(post_center_limit_range=RANGE, max_per_img=100, max_pool_nms=False, min_radius=[4, 12, 10],
                      score_threshold=0.0, out_size_factor=8, voxel_size=VOXEL[:2], nms_type="rotate",
                      pre_max_size=100, post_max_size=30, nms_thr=0.2))


def _boxes(n, g):
    xyz = torch.stack([torch.rand(n, generator=g) * 45 + 3, torch.rand(n, generator=g) * 40 - 20,
                       torch.rand(n, generator=g) - 2], 1)
    lwh = torch.tensor([3.9, 1.6, 1.56]) * (0.3 + torch.rand(n, 3, generator=g))
    return torch.cat([xyz, lwh, torch.rand(n, 1, generator=g) * 6 - 3], 1)


def test_losses_and_decoding_equal_mmdet3d_centerhead_with_zero_velocity():
    require_mmdet3d()
    import mssf_examples.mmdet3d.plugin  # noqa: F401  (registers the head)
    from mmdet3d.registry import MODELS
    from mmdet3d.structures import LiDARInstance3DBoxes
    from mmengine.registry import init_default_scope
    from mmengine.structures import InstanceData

    init_default_scope("mmdet3d")
    torch.manual_seed(0)
    ours = MODELS.build(head_cfg("CenterHeadWithoutVelocity", velocity=False))
    ref = MODELS.build(head_cfg("CenterHead", velocity=True))
    missing, unexpected = ref.load_state_dict(ours.state_dict(), strict=False)
    assert not unexpected and missing and all(".vel." in k for k in missing)  # only the velocity branch is its own
    g = torch.Generator().manual_seed(1)
    gts7, gts9 = [], []
    for n in (5, 3):
        boxes = _boxes(n, g)
        labels = torch.randint(0, 3, (n,), generator=g)
        gts7.append(InstanceData(bboxes_3d=LiDARInstance3DBoxes(boxes), labels_3d=labels))
        gts9.append(InstanceData(bboxes_3d=LiDARInstance3DBoxes(torch.cat([boxes, torch.zeros(n, 2)], 1), box_dim=9),
                                 labels_3d=labels))
    x = [torch.randn(2, 32, 16, 16, generator=g)]
    ours.eval(), ref.eval()  # (decoding first: a training forward moves the BN statistics)
    metas = [dict(box_type_3d=LiDARInstance3DBoxes)] * 2
    with torch.no_grad():
        p_ours = ours.predict_by_feat(ours(x), metas)
        p_ref = ref.predict_by_feat(ref(x), metas)
    for a, b in zip(p_ours, p_ref):
        assert a.bboxes_3d.tensor.shape[1] == 7 and len(a.scores_3d) > 0
        torch.testing.assert_close(a.bboxes_3d.tensor, b.bboxes_3d.tensor[:, :7])
        torch.testing.assert_close(a.scores_3d, b.scores_3d)
        assert torch.equal(a.labels_3d, b.labels_3d)
    ours.train(), ref.train()
    got = ours.loss_by_feat(ours(x), gts7)
    want = ref.loss_by_feat(ref(x), gts9)
    assert set(got) == set(want) == {f"task{i}.{k}" for i in range(3) for k in ("loss_heatmap", "loss_bbox")}
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-6, atol=1e-7)
    assert all(float(v) > 0 for v in got.values())
    with pytest.raises(ValueError):  # stock CenterHead unpacks a velocity from every box
        ref.loss_by_feat(ref(x), gts7)


def test_refuses_a_velocity_branch_and_other_code_weights():
    require_mmdet3d()
    import mssf_examples.mmdet3d.plugin  # noqa: F401
    from mmdet3d.registry import MODELS
    from mmengine.registry import init_default_scope

    from mssf_blocks.errors import MSSFError

    init_default_scope("mmdet3d")
    with pytest.raises(MSSFError, match="common_heads: CenterHeadWithoutVelocity predicts no velocity"):
        MODELS.build(dict(head_cfg("CenterHeadWithoutVelocity", velocity=True), train_cfg=None))
    cfg = head_cfg("CenterHeadWithoutVelocity", velocity=False)
    cfg["train_cfg"]["code_weights"] = [1.0] * 10
    with pytest.raises(MSSFError, match="code_weights: expected 8 weights"):
        MODELS.build(cfg)
