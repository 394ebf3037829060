"""Detection heads: output layout, hand-built decodes, zero-GT samples, and fitting one box on fixed
random features (loss goes down, the decode finds the box)."""

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_examples.models.heads import VOD_ANCHOR_SIZES, AnchorHead, BEVGrid, CenterHead, SparseCenterHead, make_anchors

GRID = BEVGrid(0.0, -4.0, 8.0, 4.0, 16, 16)  # 0.5 m cells
GT_BOX = torch.tensor([[3.3, 0.2, -0.6, 3.9, 1.6, 1.56, 0.3]])


@pytest.fixture(autouse=True)
def one_thread():
    # Tiny tensors: on a shared 2-core machine OpenMP spinning costs far more than the work itself.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _fit(head, inputs, steps, lr):
    opt = torch.optim.Adam(head.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        parts = head.loss(head(*inputs), [GT_BOX], [torch.tensor([0])])
        total = sum(parts.values())
        losses.append(float(total.detach()))
        opt.zero_grad()
        total.backward()
        opt.step()
    head.eval()
    with torch.no_grad():
        detections = head.decode(head(*inputs))
    return losses, detections


def _assert_close_to_gt(det, centre_tol, size_rtol, yaw_tol):
    assert det["boxes"].shape[0] >= 1
    box = det["boxes"][0]  # the best-scored detection
    gt = GT_BOX[0]
    assert float((box[:3] - gt[:3]).norm()) < centre_tol, (box, gt)
    assert float(((box[3:6] - gt[3:6]).abs() / gt[3:6]).max()) < size_rtol, (box, gt)
    assert abs(math.remainder(float(box[6] - gt[6]), 2 * math.pi)) < yaw_tol, (box, gt)
    assert int(det["labels"][0]) == 0


def _check_detections(dets, batch_size, max_detections):
    assert isinstance(dets, list) and len(dets) == batch_size
    for det in dets:
        k = det["boxes"].shape[0]
        assert det["boxes"].shape == (k, 7) and det["scores"].shape == (k,) and det["labels"].shape == (k,)
        assert k <= max_detections
        assert det["labels"].dtype == torch.long
        assert bool((det["scores"][:-1] >= det["scores"][1:]).all())


# ----------------------------------------------------------------------------------------------- anchor


def test_anchor_layout_matches_conv_output():
    grid = BEVGrid(0.0, 0.0, 2.0, 4.0, 2, 2)  # cells 1 x 2 m
    anchors, classes = make_anchors(grid, [(4, 2, 1), (1, 1, 2)], [-1.0, -0.5], [0.0, math.pi / 2])
    # index = ((row * nx + col) * K + class) * R + rot
    a = ((1 * 2 + 0) * 2 + 1) * 2 + 1
    torch.testing.assert_close(anchors[a], torch.tensor([0.5, 3.0, -0.5, 1.0, 1.0, 2.0, math.pi / 2]))
    assert int(classes[a]) == 1 and anchors.shape == (16, 7)
    head = AnchorHead(3, grid, [(4, 2, 1), (1, 1, 2)], [-1.0, -0.5])
    bev = torch.randn(1, 3, 2, 2)
    preds = head(bev)
    raw = head.conv_box(bev)  # (1, 4 anchors * 7, ny, nx)
    j = 1 * 2 + 1  # anchor within the location
    torch.testing.assert_close(preds["box"][0, a], raw[0, j * 7 : (j + 1) * 7, 1, 0])
    assert preds["cls"].shape == (1, 16, 2) and preds["dir"].shape == (1, 16, 2)


def test_anchor_direction_bins_hand_worked():
    grid = BEVGrid(0.0, 0.0, 1.0, 1.0, 1, 1)
    head = AnchorHead(2, grid, [(4, 2, 1)], [0.0], rotations=(0.0,))
    box = torch.zeros(2, 1, 7)
    box[..., 6] = 0.3  # raw yaw 0.3 on a yaw-0 anchor
    dirs = torch.tensor([[[5.0, -5.0]], [[-5.0, 5.0]]])  # sample 0: bin 0, sample 1: bin 1
    boxes = head.decode_boxes({"box": box, "dir": dirs, "cls": torch.zeros(2, 1, 1)})
    # (0.3 - pi/4) mod pi = 0.3 - pi/4 + pi -> + pi/4 + k * pi: bin 0 -> 0.3 + pi = 0.3 - pi; bin 1 -> 0.3.
    torch.testing.assert_close(boxes[:, 0, 6], torch.tensor([0.3 - math.pi, 0.3]))
    # Training target of a yaw-0.3 box: (0.3 - pi/4) mod 2 pi = 5.73 -> bin 1 (the one that decodes to 0.3).
    head.conv_dir.weight.data.zero_()
    head.conv_dir.bias.data = torch.tensor([0.0, 10.0])  # predicts bin 1 with near certainty
    gt = torch.tensor([[0.5, 0.5, 0.0, 4.0, 2.0, 1.0, 0.3]])
    loss = head.loss(head(torch.zeros(1, 2, 1, 1)), [gt], [torch.tensor([0])])
    assert float(loss["dir"].detach()) < 1e-3
    head.conv_dir.bias.data = torch.tensor([10.0, 0.0])
    assert float(head.loss(head(torch.zeros(1, 2, 1, 1)), [gt], [torch.tensor([0])])["dir"].detach()) > 1.0


def test_anchor_head_fits_one_box():
    torch.manual_seed(0)
    head = AnchorHead(32, GRID, VOD_ANCHOR_SIZES, [-0.6, -0.6, -0.6], matched_thresholds=[0.6, 0.5, 0.5],
                      unmatched_thresholds=[0.45, 0.35, 0.35])
    losses, dets = _fit(head, (torch.randn(1, 32, 16, 16),), steps=60, lr=0.02)
    assert losses[-1] < 0.2 * losses[0], losses
    _check_detections(dets, 1, 100)
    _assert_close_to_gt(dets[0], centre_tol=0.25, size_rtol=0.1, yaw_tol=0.1)


# ----------------------------------------------------------------------------------------------- centre


def test_center_decode_hand_built():
    head = CenterHead(4, GRID, num_classes=2)
    hm = torch.full((1, 2, 16, 16), -10.0)
    hm[0, 1, 8, 6] = 5.0  # a peak of class 1 at (row 8, col 6)
    hm[0, 1, 8, 7] = 3.0  # its neighbour: not a local maximum -> dropped by the 3x3 max-pool
    hm[0, 0, 2, 2] = 1.0  # a second, weaker peak of class 0
    preds = {name: torch.zeros(1, c, 16, 16) for name, c in (("center", 2), ("center_z", 1), ("dim", 3), ("rot", 2))}
    preds["hm"] = hm
    preds["center"][0, :, 8, 6] = torch.tensor([0.6, 0.4])
    preds["center_z"][0, 0, 8, 6] = -0.5
    preds["dim"][0, :, 8, 6] = torch.log(torch.tensor([4.0, 2.0, 1.5]))
    preds["rot"][0, :, 8, 6] = torch.tensor([math.sin(1.0), math.cos(1.0)])
    preds["rot"][0, 1, 2, 2] = 1.0  # yaw 0 at the weak peak
    dets = head.decode(preds, score_threshold=0.1, nms_iou=None)
    _check_detections(dets, 1, 100)
    assert dets[0]["labels"].tolist() == [1, 0]
    # x = (6 + 0.6) * 0.5 + 0 = 3.3, y = (8 + 0.4) * 0.5 - 4 = 0.2
    torch.testing.assert_close(dets[0]["boxes"][0], torch.tensor([3.3, 0.2, -0.5, 4.0, 2.0, 1.5, 1.0]))
    torch.testing.assert_close(dets[0]["boxes"][1], torch.tensor([1.0, -3.0, 0.0, 1.0, 1.0, 1.0, 0.0]))
    torch.testing.assert_close(dets[0]["scores"], torch.sigmoid(torch.tensor([5.0, 1.0])))
    assert head.decode(preds, score_threshold=0.8)[0]["boxes"].shape == (1, 7)
    assert head.decode(preds, max_detections=1)[0]["labels"].tolist() == [1]


def test_center_head_fits_one_box():
    torch.manual_seed(0)
    head = CenterHead(16, GRID, num_classes=3, head_channels=32)
    losses, dets = _fit(head, (torch.randn(1, 16, 16, 16),), steps=60, lr=0.01)
    assert losses[-1] < 0.2 * losses[0], losses
    _check_detections(dets, 1, 100)
    _assert_close_to_gt(dets[0], centre_tol=0.25, size_rtol=0.2, yaw_tol=0.15)


# ----------------------------------------------------------------------------------------------- sparse


def _voxels(seed):
    gen = torch.Generator().manual_seed(seed)
    cells = torch.randperm(256, generator=gen)[:60]
    coords = torch.stack([torch.zeros(60, dtype=torch.long), cells // 16, cells % 16], 1)
    coords = torch.unique(torch.cat([coords, torch.tensor([[0, 8, 6]])]), dim=0)  # the GT centre's cell
    return coords.to(torch.int32)


def test_sparse_decode_hand_built():
    head = SparseCenterHead(4, GRID, num_classes=2)
    coords = torch.tensor([[0, 8, 7], [1, 2, 2], [0, 3, 3]], dtype=torch.int32)
    preds = {"hm": torch.full((3, 2), -10.0), "center": torch.zeros(3, 2), "center_z": torch.zeros(3, 1),
             "dim": torch.zeros(3, 3), "rot": torch.tensor([[0.0, 1.0]] * 3), "coords": coords, "batch_size": 2}
    preds["hm"][0, 1] = 4.0
    preds["hm"][1, 0] = 2.0
    preds["center"][0] = torch.tensor([-0.4, 0.4])  # offsets may leave the voxel's cell (nearest-voxel targets)
    dets = head.decode(preds)
    _check_detections(dets, 2, 100)
    torch.testing.assert_close(dets[0]["boxes"], torch.tensor([[3.3, 0.2, 0.0, 1.0, 1.0, 1.0, 0.0]]))
    torch.testing.assert_close(dets[1]["boxes"], torch.tensor([[1.0, -3.0, 0.0, 1.0, 1.0, 1.0, 0.0]]))
    assert dets[0]["labels"].tolist() == [1] and dets[1]["labels"].tolist() == [0]


def test_sparse_center_head_fits_one_box():
    torch.manual_seed(0)
    head = SparseCenterHead(16, GRID, num_classes=3, head_channels=32)
    coords = _voxels(0)
    losses, dets = _fit(head, (torch.randn(coords.shape[0], 16), coords, 1), steps=60, lr=0.01)
    assert losses[-1] < 0.2 * losses[0], losses
    _check_detections(dets, 1, 100)
    _assert_close_to_gt(dets[0], centre_tol=0.25, size_rtol=0.2, yaw_tol=0.15)


# ------------------------------------------------------------------------------------------ all heads


def _heads_and_inputs():
    torch.manual_seed(1)
    coords = torch.cat([_voxels(1), _voxels(2)[:20]])
    coords[61:, 0] = 1
    return [
        (AnchorHead(8, GRID, VOD_ANCHOR_SIZES, [-0.6] * 3), (torch.randn(2, 8, 16, 16),)),
        (AnchorHead(8, GRID, VOD_ANCHOR_SIZES, [-0.6] * 3, encode_angle_by_sincos=True,
                    use_direction_classifier=False), (torch.randn(2, 8, 16, 16),)),
        (CenterHead(8, GRID, 3, head_channels=16), (torch.randn(2, 8, 16, 16),)),
        (SparseCenterHead(8, GRID, 3, head_channels=16), (torch.randn(coords.shape[0], 8), coords, 2)),
    ]


def test_zero_gt_sample_and_decode_shapes():
    gt_boxes = [GT_BOX, torch.zeros(0, 7)]
    gt_labels = [torch.tensor([0]), torch.zeros(0, dtype=torch.long)]
    for head, inputs in _heads_and_inputs():
        preds = head(*inputs)
        losses = head.loss(preds, gt_boxes, gt_labels)
        assert {"cls", "reg"} <= set(losses)
        total = sum(losses.values())
        assert bool(torch.isfinite(total))
        total.backward()
        none = head.loss(head(*inputs), [torch.zeros(0, 7)] * 2, [torch.zeros(0, dtype=torch.long)] * 2)
        assert float(none["reg"].detach()) == 0.0 and float(none["cls"].detach()) > 0.0
        _check_detections(head.decode(preds, score_threshold=0.0, max_detections=5), 2, 5)
        _check_detections(head.decode(preds, score_threshold=0.0, nms_iou=None, max_detections=7), 2, 7)
        assert all(d["boxes"].shape == (0, 7) for d in head.decode(preds, score_threshold=1.0))


def test_bad_input_raises():
    anchor = AnchorHead(8, GRID, VOD_ANCHOR_SIZES, [-0.6] * 3)
    with pytest.raises(MSSFError, match="bev"):
        anchor(torch.randn(1, 8, 16, 15))
    preds = anchor(torch.randn(1, 8, 16, 16))
    with pytest.raises(MSSFError, match="gt_boxes"):
        anchor.loss(preds, [GT_BOX, GT_BOX], [torch.tensor([0])] * 2)
    with pytest.raises(MSSFError, match="gt_labels"):
        anchor.loss(preds, [GT_BOX], [torch.tensor([5])])
    with pytest.raises(MSSFError, match="anchor_z_centers"):
        AnchorHead(8, GRID, VOD_ANCHOR_SIZES, [-0.6])
    with pytest.raises(MSSFError, match="nms_iou"):
        anchor.decode(preds, nms_iou=2.0)
    sparse = SparseCenterHead(8, GRID, 3)
    with pytest.raises(MSSFError, match="coords"):
        sparse(torch.randn(2, 8), torch.tensor([[0, 1, 1], [0, 16, 1]], dtype=torch.int32), 1)
    with pytest.raises(MSSFError, match="grid"):
        CenterHead(8, (0, 0, 1, 1, 4, 4), 3)
