"""Feature-blurring diagnostics on hand-built scenes with hand-counted classes."""

from __future__ import annotations

import sys

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks.diagnostics import (
    BlurClassification,
    blur_curves,
    blur_ratio,
    classify_feature_blurring,
    classify_projection,
    foreground_recall,
    instance_foreground_counts,
    mask_blur_projection,
    mask_blur_valid,
    mask_blurred_features,
    plot_blur_curves,
)
from mssf_blocks.errors import MSSFError
from mssf_blocks.geometry import CentroidProjection

H, W, FOCAL, CX, CY = 100, 200, 100.0, 100.0, 50.0


def project(p):
    """Pinhole camera looking along +x: u = cx - f y / x, v = cy - f z / x; normalised uv, valid."""
    x, y, z = p
    if x <= 1e-5:
        return [-1.0, -1.0], False
    u, v = CX - FOCAL * y / x, CY - FOCAL * z / x
    uv = [(u + 0.5) / W, (v + 0.5) / H]
    return uv, 0 <= uv[0] <= 1 and 0 <= uv[1] <= 1


# A car-sized box 10 m ahead, and a deliberately tight 2D box (u in [92, 108], v in [40, 60]).
BOX3D = [10.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]
BOX2D = [92.0, 40.0, 108.0, 60.0]
POINTS = {
    "fore3d": [[10.0, -0.5, 0.0], [10.0, 0.0, 0.2], [10.5, 0.5, -0.3]],  # in the 3D box, project in 2D box
    "blurred": [[5.0, 0.0, 0.0], [5.0, 0.2, 0.1], [20.0, 0.5, 0.0], [20.0, -1.0, 0.5]],  # in front / behind
    "box3d_only": [[9.1, 0.9, 0.0]],  # in the 3D box but projects at u = 90.1, outside the tight 2D box
    "background": [[10.0, 5.0, 0.0], [30.0, -20.0, 0.0]],
    "behind_camera": [[-5.0, 0.0, 0.0]],
}
SCORES = {
    "fore3d": [0.9, 0.8, 0.3],
    "blurred": [0.6, 0.2, 0.95, 0.1],
    "box3d_only": [0.7],
    "background": [0.99, 0.05],
    "behind_camera": [0.5],
}


def scene(dtype=torch.float64):
    pts, uv, valid, scores, kinds = [], [], [], [], []
    for kind, group in POINTS.items():
        for p, s in zip(group, SCORES[kind]):
            q, ok = project(p)
            pts.append(p)
            uv.append(q)
            valid.append(ok)
            scores.append(s)
            kinds.append(kind)
    return (torch.tensor(pts, dtype=dtype), torch.tensor(uv, dtype=dtype)[:, None], torch.tensor(valid)[:, None],
            torch.tensor(scores, dtype=dtype), kinds)


def test_hand_scene_counts_with_2d_boxes():
    pts, uv, valid, _, kinds = scene()
    batch = torch.zeros(len(pts), dtype=torch.long)
    cls = classify_feature_blurring(pts, batch, uv, [torch.tensor([BOX3D])],
                                    boxes_2d=[torch.tensor([BOX2D])], image_size=(H, W), valid=valid)
    assert cls.counts() == {"points": 11, "fore2d": 7, "fore3d": 3, "blurred": 4, "in_box3d": 4}
    assert [k for k, f in zip(kinds, cls.fore3d.tolist()) if f] == ["fore3d"] * 3
    assert [k for k, f in zip(kinds, cls.blurred.tolist()) if f] == ["blurred"] * 4
    assert [k for k, f in zip(kinds, cls.in_box3d.tolist()) if f] == ["fore3d"] * 3 + ["box3d_only"]


def test_hand_scene_with_masks_any_resolution_and_bottom_origin():
    pts, uv, valid, _, _ = scene()
    batch = torch.zeros(len(pts), dtype=torch.int32)
    mask = torch.zeros(1, H, W, dtype=torch.bool)
    mask[0, 40:61, 92:109] = True  # the pixels of the 2D box
    box_bottom = torch.tensor([[10.0, 0.0, -1.0, 2.0, 2.0, 2.0, 0.0]])  # same box, z at the bottom face
    cls = classify_feature_blurring(pts, batch, uv[:, 0], [box_bottom], masks=mask, valid=valid[:, 0],
                                    origin="bottom")
    assert (cls.n_fore2d, cls.n_fore3d, cls.n_blurred) == (7, 3, 4)
    # A half-resolution mask (each cell covers 2 x 2 pixels) of the same region gives the same classes
    # here (no point within 2 pixels of the mask edge).
    half = torch.zeros(1, 1, H // 2, W // 2, dtype=torch.bool)
    half[0, 0, 20:31, 46:55] = True
    cls_half = classify_feature_blurring(pts, batch, uv, [box_bottom], masks=half, valid=valid,
                                         origin="bottom")
    assert torch.equal(cls_half.fore2d, cls.fore2d)


def test_two_cameras_and_a_sample_without_boxes():
    pts, uv, valid, _, _ = scene()
    n = len(pts)
    # Sample 0 sees the scene in camera 1 only (camera 0 looks elsewhere: its uv are invalid);
    # sample 1 is the same points but without any box.
    uv2 = torch.cat([torch.full_like(uv, -1.0), uv], dim=1)
    valid2 = torch.cat([torch.zeros_like(valid), valid], dim=1)
    pts_b = torch.cat([pts, pts])
    uv_b = torch.cat([uv2, uv2])
    valid_b = torch.cat([valid2, valid2])
    batch = torch.tensor([0] * n + [1] * n)
    cls = classify_feature_blurring(
        pts_b, batch, uv_b, [torch.tensor([BOX3D]), torch.zeros(0, 7, dtype=torch.float64)],
        boxes_2d=[torch.tensor([[1.0] + BOX2D]), torch.zeros(0, 5)], image_size=(H, W), valid=valid_b)
    assert (cls.n_fore2d, cls.n_fore3d, cls.n_blurred) == (7, 3, 4)
    assert not bool(cls.fore2d[n:].any()) and not bool(cls.in_box3d[n:].any())
    # The box in camera 0 instead: nothing is 2D foreground (camera 0 projections are invalid).
    cls0 = classify_feature_blurring(
        pts_b, batch, uv_b, [torch.tensor([BOX3D]), torch.zeros(0, 7)],
        boxes_2d=[torch.tensor([[0.0] + BOX2D]), torch.zeros(0, 5)], image_size=(H, W), valid=valid_b)
    assert cls0.n_fore2d == 0


def test_curves_hand_counted():
    pts, uv, valid, scores, _ = scene()
    cls = classify_feature_blurring(pts, torch.zeros(len(pts), dtype=torch.long), uv, [torch.tensor([BOX3D])],
                                    boxes_2d=[torch.tensor([BOX2D])], image_size=(H, W), valid=valid)
    # blurred scores 0.6, 0.2, 0.95, 0.1; 3D-foreground scores 0.9, 0.8, 0.3; n_fore2d = 7.
    assert float(blur_ratio(scores, cls, 0.0)) == pytest.approx(4 / 7)
    assert float(foreground_recall(scores, cls, 0.0)) == pytest.approx(3 / 7)
    assert float(blur_ratio(scores, cls, 0.5)) == pytest.approx(2 / 7)
    assert float(foreground_recall(scores, cls, 0.5)) == pytest.approx(2 / 7)
    # "above" the threshold is strict: 0.9 is not above 0.9.
    assert float(blur_ratio(scores, cls, 0.9)) == pytest.approx(1 / 7)
    assert float(foreground_recall(scores, cls, 0.9)) == 0.0
    taus = torch.tensor([0.0, 0.25, 0.5, 0.85, 1.0])
    curves = blur_curves(scores, cls, taus)
    assert curves.blur_ratio.tolist() == pytest.approx([4 / 7, 2 / 7, 2 / 7, 1 / 7, 0.0])
    assert curves.foreground_recall.tolist() == pytest.approx([3 / 7, 3 / 7, 2 / 7, 1 / 7, 0.0])
    assert (curves.n_fore2d, curves.n_fore3d, curves.n_blurred) == (7, 3, 4)
    default = blur_curves(scores.float(), cls)
    assert default.tau.shape == (101,) and float(default.blur_ratio[0] + default.foreground_recall[0]) == 1.0
    assert bool((default.blur_ratio[1:] <= default.blur_ratio[:-1]).all())


def test_curves_from_masks_constructor_and_errors():
    cls = BlurClassification.from_masks(torch.tensor([True, True, False, True]),
                                        torch.tensor([True, False, True, False]))
    assert cls.fore3d.tolist() == [True, False, False, False]
    assert cls.blurred.tolist() == [False, True, False, True]
    s = torch.tensor([0.2, 0.4, 0.9, 0.6])
    assert float(blur_ratio(s, cls, 0.3)) == pytest.approx(2 / 3)
    assert float(foreground_recall(s, cls, 0.3)) == 0.0
    with pytest.raises(MSSFError, match="scores"):
        blur_ratio(torch.zeros(3), cls, 0.5)
    with pytest.raises(MSSFError, match="classes"):
        blur_ratio(s, (cls.fore2d, cls.fore3d), 0.5)
    none = BlurClassification.from_masks(torch.zeros(4, dtype=torch.bool), torch.ones(4, dtype=torch.bool))
    with pytest.raises(MSSFError, match="n_fore2d"):
        foreground_recall(s, none, 0.5)
    with pytest.raises(MSSFError, match="tau"):
        blur_ratio(s, cls, float("nan"))


def test_mask_blur_projection_gives_zero_image_features():
    pts, uv, valid, _, _ = scene()
    n = len(pts)
    cls = classify_feature_blurring(pts, torch.zeros(n, dtype=torch.long), uv, [torch.tensor([BOX3D])],
                                    boxes_2d=[torch.tensor([BOX2D])], image_size=(H, W), valid=valid)
    proj = CentroidProjection(uv=uv, depth=pts[:, :1], valid=valid, centroid=pts,
                              has_points=torch.ones(n, dtype=torch.bool), batch_index=torch.zeros(n, dtype=torch.long))
    masked = mask_blur_projection(proj, cls)
    assert torch.equal(masked.valid, valid & ~cls.blurred[:, None])
    assert torch.equal(mask_blur_valid(valid, cls.blurred), masked.valid)
    assert torch.equal(masked.uv[~cls.blurred], uv[~cls.blurred])
    # Bilinear sampling (align_corners=False, zero padding) of a constant image at the masked uv.
    image = torch.ones(1, 3, H, W, dtype=torch.float64)
    grid = (masked.uv[:, 0] * 2 - 1)[None, :, None, :]
    sampled = F.grid_sample(image, grid, align_corners=False, padding_mode="zeros")[0, :, :, 0].T
    assert float(sampled[cls.blurred].abs().sum()) == 0.0
    assert bool((sampled[cls.fore3d] > 0.99).all())
    feats = torch.ones(n, 2, 4, requires_grad=True)
    out = mask_blurred_features(feats, cls)
    out.sum().backward()
    assert float(out.detach()[cls.blurred].sum()) == 0 and float(feats.grad[cls.blurred].sum()) == 0
    assert float(out.detach()[~cls.blurred].sum()) == (n - 4) * 8
    with pytest.raises(MSSFError, match="blurred"):
        mask_blur_valid(valid, cls.blurred[:3])


def test_classify_projection_matches_direct_call():
    pts, uv, valid, _, _ = scene()
    n = len(pts)
    proj = CentroidProjection(uv=uv, depth=pts[:, :1], valid=valid, centroid=pts,
                              has_points=torch.ones(n, dtype=torch.bool), batch_index=torch.zeros(n, dtype=torch.long))
    cls = classify_projection(proj, [torch.tensor([BOX3D])], boxes_2d=[torch.tensor([BOX2D])], image_size=(H, W))
    assert (cls.n_fore2d, cls.n_fore3d, cls.n_blurred) == (7, 3, 4)


def test_instance_foreground_counts():
    pts, uv, valid, _, _ = scene()
    n = len(pts)
    # Second instance: a pedestrian-sized box at (10, 5, 0) with a 2D box around u = 50.
    box3d = torch.tensor([BOX3D, [10.0, 5.0, 0.0, 0.6, 0.6, 1.8, 0.3]])
    box2d = torch.tensor([BOX2D, [45.0, 40.0, 55.0, 60.0]])
    n2, n3 = instance_foreground_counts(pts, torch.zeros(n, dtype=torch.long), uv, (H, W), [box3d], [box2d],
                                        valid=valid)
    # Object 0: 7 points project in its 2D box, 3 of them in its 3D box. Object 1: the point
    # (10, 5, 0) projects at u = 50 and is in its 3D box.
    assert n2.tolist() == [7, 1] and n3.tolist() == [3, 1]
    with pytest.raises(MSSFError, match=r"boxes_2d\[0\]"):
        instance_foreground_counts(pts, torch.zeros(n, dtype=torch.long), uv, (H, W), [box3d], [box2d[:1]])


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"boxes_2d": None, "masks": None}, "boxes_2d, masks"),
        ({"image_size": None}, "image_size"),
        ({"boxes_2d": [torch.tensor([[0.0, 0, 1, 1, 1, 1]])]}, r"boxes_2d\[0\]"),
        ({"boxes_2d": [torch.tensor([[10.0, 0, 1, 1]])]}, r"boxes_2d\[0\]"),
        ({"boxes_2d": [torch.tensor([[2.0, 0, 0, 1, 1]])]}, r"boxes_2d\[0\]"),
        ({"boxes_2d": []}, "boxes_2d"),
        ({"gt_boxes": torch.zeros(1, 1, 7)}, "gt_boxes"),
        ({"gt_boxes": [torch.zeros(1, 6)]}, r"gt_boxes\[0\]"),
        ({"valid": torch.ones(3, 1, dtype=torch.bool)}, "valid"),
        ({"batch_index": torch.ones(11, dtype=torch.long)}, "batch_index"),
        ({"masks": torch.zeros(1, H, W), "boxes_2d": None}, "masks"),
        ({"masks": torch.zeros(2, H, W, dtype=torch.bool), "boxes_2d": None}, "masks"),
    ],
)
def test_bad_input(kwargs, match):
    pts, uv, valid, _, _ = scene()
    args = dict(centroids=pts, batch_index=torch.zeros(len(pts), dtype=torch.long), uv=uv,
                gt_boxes=[torch.tensor([BOX3D])], boxes_2d=[torch.tensor([BOX2D])], image_size=(H, W),
                valid=valid)
    args.update(kwargs)
    with pytest.raises(MSSFError, match=match):
        classify_feature_blurring(**args)


def test_plot_writes_png(tmp_path):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    pts, uv, valid, scores, _ = scene()
    cls = classify_feature_blurring(pts, torch.zeros(len(pts), dtype=torch.long), uv, [torch.tensor([BOX3D])],
                                    boxes_2d=[torch.tensor([BOX2D])], image_size=(H, W), valid=valid)
    path = tmp_path / "curves.png"
    fig = plot_blur_curves({"a": blur_curves(scores, cls), "b": blur_curves(scores * 0.5, cls)}, path=str(path))
    assert path.stat().st_size > 1000 and len(fig.axes) == 2
    with pytest.raises(MSSFError, match="curves"):
        plot_blur_curves({})


def test_plot_without_matplotlib_says_so(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    monkeypatch.setitem(sys.modules, "matplotlib.pyplot", None)
    cls = BlurClassification.from_masks(torch.tensor([True]), torch.tensor([True]))
    with pytest.raises(ImportError, match="pip install matplotlib"):
        plot_blur_curves(blur_curves(torch.tensor([0.5]), cls))
