"""The authors' test-time decoding switches (docs/differences.md row 27).

* ``AnchorHead.decode(multi_class=True)``: mmdet3d's ``Anchor3DHead`` (their MSSF-PP): top ``nms_pre``
  anchors by best score, then every class above the threshold is a box.
* ``SparseCenterHead.decode(class_agnostic_nms=True, center_range=...)``: their ``VoxelNeXtHead``.

References: hand-worked cases, and mmdet3d's own ``box3d_multiclass_nms`` on the same inputs.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.models.heads import AnchorHead, BEVGrid, SparseCenterHead
from mssf_examples.models.ops.boxes import decode_center

sys.path.insert(0, str(Path(__file__).parents[2] / "integrations"))
from mmdet3d_vod_tree import require_mmdet3d  # noqa: E402


def _logit(p: float) -> float:
    return math.log(p / (1 - p))


def _one_cell_anchor_head() -> AnchorHead:
    # one cell at (0.5, 0.5), two classes, one yaw: anchor 0 = class 0 (4 x 2 x 1), anchor 1 = class 1 (1 x 1 x 2)
    return AnchorHead(2, BEVGrid(0.0, 0.0, 1.0, 1.0, 1, 1), [(4, 2, 1), (1, 1, 2)], [0.0, 0.0], rotations=(0.0,))


def _anchor_preds(probs):
    cls = torch.tensor([[[_logit(p) for p in row] for row in probs]], dtype=torch.float64)
    return {"cls": cls, "box": torch.zeros(1, 2, 7, dtype=torch.float64),
            "dir": torch.zeros(1, 2, 2, dtype=torch.float64)}


def test_multi_class_anchor_gives_a_box_per_class_above_threshold():
    head = _one_cell_anchor_head()
    preds = _anchor_preds([[0.9, 0.6], [0.05, 0.05]])  # anchor 0: both classes above 0.1; anchor 1: none
    ours = head.decode(preds, 0.1, 0.01, 50)[0]
    assert ours["labels"].tolist() == [0] and ours["scores"].tolist() == pytest.approx([0.9])
    theirs = head.decode(preds, 0.1, 0.01, 50, multi_class=True)[0]
    assert theirs["labels"].tolist() == [0, 1]
    assert theirs["scores"].tolist() == pytest.approx([0.9, 0.6])
    # the same box for both classes: anchor 0 (centre (0.5, 0.5, 0), 4 x 2 x 1); direction bin 0 with the
    # default offset pi / 4 turns yaw 0 into pi, written -pi
    expected = torch.tensor([0.5, 0.5, 0.0, 4.0, 2.0, 1.0, -math.pi], dtype=torch.float64)
    for box in theirs["boxes"]:
        assert torch.allclose(box, expected, atol=1e-12)


def test_multi_class_takes_top_anchors_by_best_score_first():
    head = _one_cell_anchor_head()
    head.nms_pre = 1
    # anchor 1's best (0.8) is below anchor 0's (0.9): only anchor 0 passes the top 1, with both its classes
    preds = _anchor_preds([[0.9, 0.3], [0.05, 0.8]])
    theirs = head.decode(preds, 0.1, 0.01, 50, multi_class=True)[0]
    assert theirs["labels"].tolist() == [0, 1] and theirs["scores"].tolist() == pytest.approx([0.9, 0.3])
    head.nms_pre = 2  # both anchors: class 1 of anchor 1 (0.8) and of anchor 0 (0.3) overlap (IoU 1/8 > 0.01)
    theirs = head.decode(preds, 0.1, 0.01, 50, multi_class=True)[0]
    assert theirs["labels"].tolist() == [0, 1] and theirs["scores"].tolist() == pytest.approx([0.9, 0.8])
    with pytest.raises(MSSFError, match="multi_class"):
        head.decode(preds, 0.1, 0.01, 50, multi_class=1)


def _sparse_preds(rows):
    """``rows``: (col, row, class probs, dx, dy): one voxel each, code offsets 0.5 (cell centre), z 0, yaw 0."""
    m = len(rows)
    f64 = torch.float64
    return {"hm": torch.tensor([[_logit(p) for p in r[2]] for r in rows], dtype=f64),
            "center": torch.full((m, 2), 0.5, dtype=f64), "center_z": torch.zeros(m, 1, dtype=f64),
            "dim": torch.tensor([[math.log(r[3]), math.log(r[4]), 0.0] for r in rows], dtype=f64),
            "rot": torch.tensor([[0.0, 1.0]] * m, dtype=f64),
            "coords": torch.tensor([[0, r[1], r[0]] for r in rows]), "batch_size": 1}


def test_class_agnostic_nms_keeps_one_of_two_overlapping_boxes_of_different_classes():
    head = SparseCenterHead(4, BEVGrid(0.0, 0.0, 4.0, 4.0, 4, 4), num_classes=2)
    # voxels (0, 0) and (1, 0): 2 x 2 m boxes 1 m apart, IoU 1/3; class 0 at 0.9, class 1 at 0.7
    preds = _sparse_preds([(0, 0, (0.9, 0.01), 2.0, 2.0), (1, 0, (0.01, 0.7), 2.0, 2.0)])
    per_class = head.decode(preds, 0.1, 0.2, 83)[0]
    assert per_class["labels"].tolist() == [0, 1]
    agnostic = head.decode(preds, 0.1, 0.2, 83, class_agnostic_nms=True)[0]
    assert agnostic["labels"].tolist() == [0] and agnostic["scores"].tolist() == pytest.approx([0.9])


def test_center_range_drops_outside_centres_before_nms():
    head = SparseCenterHead(4, BEVGrid(0.0, 0.0, 4.0, 4.0, 4, 4), num_classes=1)
    # centres x = 0.5 and 1.5; range x <= 1.0 drops the first, the better one: it then suppresses nothing
    preds = _sparse_preds([(0, 0, (0.9,), 2.0, 2.0), (1, 0, (0.7,), 2.0, 2.0)])
    assert head.decode(preds, 0.1, 0.2, 83)[0]["scores"].tolist() == pytest.approx([0.9])
    inside = head.decode(preds, 0.1, 0.2, 83, center_range=(1.0, 0.0, -1.0, 4.0, 4.0, 1.0))[0]
    assert inside["scores"].tolist() == pytest.approx([0.7])
    assert inside["boxes"][0, 0].item() == pytest.approx(1.5)
    # bounds inclusive: a centre exactly on x1 = 1.5 stays; z outside [z0, z1] drops
    edge = head.decode(preds, 0.1, 0.2, 83, center_range=(1.5, 0.0, -1.0, 1.5, 4.0, 1.0))[0]
    assert edge["scores"].tolist() == pytest.approx([0.7])
    assert head.decode(preds, 0.1, 0.2, 83, center_range=(0.0, 0.0, 0.5, 4.0, 4.0, 1.0))[0]["scores"].numel() == 0
    with pytest.raises(MSSFError, match="center_range"):
        head.decode(preds, 0.1, 0.2, 83, center_range=(0.0, 0.0, 1.0))


def test_detector_decode_options_default_per_layout():
    pytest.importorskip("spconv")
    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.presets import tiny_preset

    p = tiny_preset()
    assert build_detector("voxelnext", p, num_fusion_blocks=0).decode_options == {}
    authors = build_detector("voxelnext", p, num_fusion_blocks=0, layout="authors")
    assert authors.decode_options == {"class_agnostic_nms": True, "center_range": tuple(p.point_cloud_range)}
    with pytest.raises(MSSFError, match="decode_options"):
        build_detector("voxelnext", p, num_fusion_blocks=0, decode_options={"multi_class": True})
    with pytest.raises(MSSFError, match="center_range"):
        build_detector("voxelnext", p, num_fusion_blocks=0, decode_options={"center_range": (0, 1)})
    with pytest.raises(MSSFError, match="decode_options"):
        build_detector("voxelnext", p, num_fusion_blocks=0, decode_options=[("class_agnostic_nms", True)])


def test_multi_class_matches_mmdet3d_box3d_multiclass_nms():
    require_mmdet3d()
    from mmdet3d.models.layers import box3d_multiclass_nms
    from mmdet3d.structures import LiDARInstance3DBoxes, xywhr2xyxyr
    from mmengine.config import ConfigDict

    torch.manual_seed(0)
    grid = BEVGrid(0.0, -4.0, 8.0, 4.0, 8, 8)
    head = AnchorHead(4, grid, [(3.9, 1.6, 1.56), (0.8, 0.6, 1.73), (1.76, 0.6, 1.73)], [-1.0, -0.6, -0.6],
                      rotations=(0.0, 1.57), nms_pre=100)
    a = head.anchors.shape[0]
    preds = {"cls": torch.randn(1, a, 3) * 2 - 2.5, "box": torch.randn(1, a, 7) * 0.3,
             "dir": torch.zeros(1, a, 2)}
    ours = head.decode(preds, 0.1, 0.01, 50, multi_class=True)[0]
    # theirs (Anchor3DHead._predict_by_feat_single): top nms_pre by best score, then box3d_multiclass_nms
    scores = torch.sigmoid(preds["cls"][0])
    top = scores.max(dim=1).values.topk(100).indices
    boxes = head.decode_boxes(preds)[0, top]
    padded = torch.cat([scores[top], scores.new_zeros(len(top), 1)], dim=1)
    bev = xywhr2xyxyr(LiDARInstance3DBoxes(boxes).bev)
    cfg = ConfigDict(use_rotate_nms=True, nms_thr=0.01)
    t_boxes, t_scores, t_labels = box3d_multiclass_nms(boxes, bev, padded, 0.1, 50, cfg)
    assert len(t_scores) > 10 and len(set(t_labels.tolist())) == 3
    order = t_scores.argsort(descending=True)
    assert ours["labels"].tolist() == t_labels[order].tolist()
    assert torch.allclose(ours["scores"], t_scores[order])
    assert torch.allclose(ours["boxes"], t_boxes[order])
    assert len(ours["scores"]) > len(head.decode(preds, 0.1, 0.01, 50)[0]["scores"])  # second classes exist


def test_voxelnext_switches_match_mmdet3d_nms_bev():
    require_mmdet3d()
    from mmdet3d.models.layers import nms_bev
    from mmdet3d.structures import LiDARInstance3DBoxes, xywhr2xyxyr

    torch.manual_seed(1)
    grid = BEVGrid(0.0, -4.0, 8.0, 4.0, 16, 16)
    head = SparseCenterHead(4, grid, num_classes=3)
    coords = torch.stack(torch.meshgrid(torch.zeros(1, dtype=torch.long), torch.arange(16), torch.arange(16),
                                        indexing="ij"), -1).reshape(-1, 3)
    m = coords.shape[0]
    preds = {"hm": torch.randn(m, 3) * 2 - 2, "center": torch.rand(m, 2) * 3 - 1, "center_z": torch.randn(m, 1),
             "dim": torch.randn(m, 3) * 0.3 + 0.3, "rot": torch.randn(m, 2), "coords": coords, "batch_size": 1}
    rng = (0.5, -3.5, -1.0, 7.5, 3.5, 1.0)
    ours = head.decode(preds, 0.02, 0.2, 83, class_agnostic_nms=True, center_range=rng)[0]
    # theirs: VoxelNeXtBBoxCoder.decode (top 500 (voxel, class), score > thr, centre in range) then one nms_bev
    heat = torch.sigmoid(preds["hm"]).flatten()
    scores, idx = heat.topk(500)
    all_boxes = decode_center(head._codes(preds), coords[:, [2, 1]], (grid.cell_x, grid.cell_y),
                              (grid.x_min, grid.y_min))  # every voxel's box (the decoding is tested elsewhere)
    cand, labels = all_boxes[idx // 3], idx % 3
    r = torch.tensor(rng)
    keep = (scores > 0.02) & (cand[:, :3] >= r[:3]).all(1) & (cand[:, :3] <= r[3:]).all(1)
    cand, scores, labels = cand[keep], scores[keep], labels[keep]
    sel = nms_bev(xywhr2xyxyr(LiDARInstance3DBoxes(cand).bev), scores, 0.2, pre_max_size=1000, post_max_size=83)
    assert 10 < len(sel) < len(cand) and int(keep.sum()) < 500
    assert ours["labels"].tolist() == labels[sel].tolist()
    assert torch.allclose(ours["scores"], scores[sel])
    assert torch.allclose(ours["boxes"], cand[sel])
