import math

import pytest
import torch

pytest.importorskip("spconv")

from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_examples.data.batch import RadarCameraBatch  # noqa: E402
from mssf_examples.models.detectors import build_detector  # noqa: E402
from mssf_examples.models.presets import TINY, TJ4D, VOD  # noqa: E402

SIZES = [(3.9, 1.6, 1.56), (0.8, 0.6, 1.73), (1.76, 0.6, 1.73)]


def make_batch(seed: int = 0, batch_size: int = 2, points_per_box: int = 15, background: int = 30) -> RadarCameraBatch:
    """A fixed radar + camera batch: three boxes per sample with points inside them, clutter, a random image.

    Points carry the VoD features ``[x, y, z, RCS, v_r, v_rc, t]``; one camera at the origin looks along +x.
    """
    g = torch.Generator().manual_seed(seed)
    points, boxes, labels = [], [], []
    for s in range(batch_size):
        bx, lb, pts = [], [], []
        for k, (cx, cy) in enumerate([(4.0, -3.0), (7.0, 2.0), (10.0, -1.0)]):
            cls = (k + s) % 3
            dx, dy, dz = SIZES[cls]
            yaw = float(torch.rand(1, generator=g)) * math.pi - math.pi / 2
            z = -1.5 + dz / 2
            bx.append([cx, cy, z, dx, dy, dz, yaw])
            lb.append(cls)
            local = (torch.rand(points_per_box, 3, generator=g) - 0.5) * torch.tensor([dx, dy, dz])
            c, sn = math.cos(yaw), math.sin(yaw)
            xy = torch.stack([local[:, 0] * c - local[:, 1] * sn, local[:, 0] * sn + local[:, 1] * c], 1)
            xyz = torch.cat([xy + torch.tensor([cx, cy]), local[:, 2:] + z], 1)
            feats = torch.cat([torch.full((points_per_box, 1), 5.0 + cls),
                               torch.randn(points_per_box, 2, generator=g) * 0.1 + cls,
                               torch.randint(0, 5, (points_per_box, 1), generator=g).float()], 1)
            pts.append(torch.cat([xyz, feats], 1))
        clutter = torch.rand(background, 3, generator=g) * torch.tensor([12.4, 12.4, 4.0]) + torch.tensor([0.2, -6.2, -2.8])
        pts.append(torch.cat([clutter, torch.randn(background, 3, generator=g),
                              torch.randint(0, 5, (background, 1), generator=g).float()], 1))
        points.append(torch.cat(pts))
        boxes.append(torch.tensor(bx))
        labels.append(torch.tensor(lb))
    l2i = torch.zeros(batch_size, 1, 3, 4)
    l2i[:, :, 0, 1], l2i[:, :, 1, 2], l2i[:, :, 2, 0] = -20.0, -20.0, 1.0  # f = 20 px, depth = x
    l2i[:, :, 0, 0], l2i[:, :, 1, 0] = 32.0, 16.0  # principal point (32, 16) of a 64 x 32 image
    return RadarCameraBatch(points=points, lidar2img=l2i, images=torch.rand(batch_size, 1, 3, 32, 64, generator=g),
                            gt_boxes=boxes, gt_labels=labels)


# Tiny tensors: intra-op threads cost far more than they save (5-10x slower steps with 2 threads on
# a loaded 2-core machine), and spconv's threaded CPU kernels are not bit-deterministic.
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def batch():
    return make_batch()


@pytest.mark.parametrize("n", [0, 2], ids=["radar_only", "fusion"])
@pytest.mark.parametrize("name", ["second", "centerpoint", "voxelnext", "pointpillars"])
def test_smoke_training_reduces_loss_and_eval_returns_boxes(name, n, batch):
    torch.manual_seed(0)
    model = build_detector(name, TINY, num_fusion_blocks=n, score_threshold=0.0, max_detections=20)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    model.train()
    totals = []
    for _ in range(20):
        losses = model(batch)
        assert ("seg" in losses) == (n > 0)
        assert all(torch.isfinite(v) for v in losses.values())
        opt.zero_grad()
        losses["loss"].backward()
        opt.step()
        totals.append(float(losses["loss"].detach()))
    assert totals[-1] < 0.5 * totals[0], totals
    model.eval()
    with torch.no_grad():
        dets = model(batch)
    assert len(dets) == 2
    for d in dets:
        k = d["boxes"].shape[0]
        assert d["boxes"].shape == (k, 7) and d["scores"].shape == (k,) and d["labels"].shape == (k,)
        assert 0 < k <= 20
        assert d["labels"].dtype == torch.long and int(d["labels"].max()) < 3
        assert torch.isfinite(d["boxes"]).all() and (d["boxes"][:, 3:6] > 0).all()


def test_precomputed_image_features_match_the_branch(batch):
    torch.manual_seed(0)
    model = build_detector("centerpoint", TINY, num_fusion_blocks=1, fusion="sff").eval()
    pre = build_detector("centerpoint", TINY, num_fusion_blocks=1, fusion="sff", image_features="precomputed").eval()
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("image_branch.")}
    pre.load_state_dict(state)
    assert pre.image_branch is None
    with torch.no_grad():
        feats = model.image_branch(batch.images)
        b2 = RadarCameraBatch(points=batch.points, lidar2img=batch.lidar2img, image_features=feats,
                              image_size=batch.image_size)
        a, _, _, _ = model.extract(batch)
        b, _, _, _ = pre.extract(b2)
    for key in a:
        torch.testing.assert_close(b[key], a[key])


def test_radar_only_ignores_images_and_fusion_needs_them(batch):
    model = build_detector("voxelnext", TINY, num_fusion_blocks=0)
    assert model.image_branch is None and model.backbone.seg_head is None
    fused = build_detector("second", TINY, num_fusion_blocks=2, image_features="precomputed")
    with pytest.raises(MSSFError, match="image_features"):
        fused(batch)


def test_bad_arguments(batch):
    with pytest.raises(MSSFError, match="name"):
        build_detector("pointrcnn", TINY)
    with pytest.raises(MSSFError, match="image_features"):
        build_detector("second", TINY, image_features="cached")
    with pytest.raises(MSSFError, match="num_fusion_blocks"):
        build_detector("pointpillars", TINY, num_fusion_blocks=4)
    bad = RadarCameraBatch(points=[p[:, :5] for p in batch.points], lidar2img=batch.lidar2img, images=batch.images)
    with pytest.raises(MSSFError, match="columns"):
        build_detector("second", TINY, num_fusion_blocks=0)(bad)


def test_batch_validation_and_radar_only_without_images(batch):
    with pytest.raises(MSSFError, match="points"):
        RadarCameraBatch(points=[], lidar2img=batch.lidar2img)
    with pytest.raises(MSSFError, match=r"points\[1\]"):
        RadarCameraBatch(points=[batch.points[0], batch.points[1][:, :5]], lidar2img=batch.lidar2img)
    with pytest.raises(MSSFError, match="lidar2img"):
        RadarCameraBatch(points=batch.points, lidar2img=batch.lidar2img[:1])
    with pytest.raises(MSSFError, match="gt_labels"):
        RadarCameraBatch(points=batch.points, lidar2img=batch.lidar2img, gt_boxes=batch.gt_boxes,
                         gt_labels=[batch.gt_labels[0], batch.gt_labels[1][:2]])
    with pytest.raises(MSSFError, match="image_size"):
        RadarCameraBatch(points=batch.points, lidar2img=batch.lidar2img, images=batch.images, image_size=(16, 16))
    with pytest.raises(MSSFError, match="image_size"):
        RadarCameraBatch(points=batch.points, lidar2img=batch.lidar2img, image_features=[torch.zeros(2, 1, 8, 8, 16)])
    radar = RadarCameraBatch(points=batch.points, lidar2img=batch.lidar2img)
    pts, pb = radar.flat_points()
    assert pts.shape == (sum(p.shape[0] for p in batch.points), 7)
    assert pb.tolist() == [0] * batch.points[0].shape[0] + [1] * batch.points[1].shape[0]
    model = build_detector("pointpillars", TINY, num_fusion_blocks=0, score_threshold=0.0).eval()
    with torch.no_grad():
        assert len(model(radar)) == 2
    with pytest.raises(MSSFError, match="images"):
        build_detector("pointpillars", TINY, num_fusion_blocks=1)(radar)


def test_presets_follow_the_paper():
    assert VOD.point_cloud_range == (0.0, -25.6, -3.0, 51.2, 25.6, 2.0)
    assert VOD.point_features == ("x", "y", "z", "RCS", "v_r", "v_rc", "t")
    assert VOD.voxel_size == (0.05, 0.05, 0.125) and VOD.pillar_size == (0.16, 0.16)
    assert VOD.anchor_sizes == ((3.9, 1.6, 1.56), (0.8, 0.6, 1.73), (1.76, 0.6, 1.73))
    assert TJ4D.point_cloud_range == (0.0, -40.0, -4.0, 70.4, 40.0, 2.0)
    assert TJ4D.pillar_range == (0.0, -39.68, -4.0, 69.12, 39.68, 2.0)
    assert TJ4D.point_features == ("x", "y", "z", "v_rc", "Power")
    assert TJ4D.class_names == ("Car", "Pedestrian", "Cyclist", "Truck")
    # the paper prints TJ4D anchors as (w, l, h); stored as (dx, dy, dz) = (l, w, h)
    assert sorted(TJ4D.anchor_sizes[0][:2]) == [1.84, 4.56] and TJ4D.anchor_sizes[3][2] == 3.47
    assert VOD.voxelnext_channels == (32, 32, 64, 128, 256, 256, 256)  # doubled VoxelNeXt
    for preset in (VOD, TJ4D):
        for lo, hi, v in zip(preset.point_cloud_range[:3], preset.point_cloud_range[3:], preset.voxel_size):
            assert abs((hi - lo) / v - round((hi - lo) / v)) < 1e-6
        for lo, hi, v in zip(preset.pillar_range[:2], preset.pillar_range[3:5], preset.pillar_size):
            assert abs((hi - lo) / v - round((hi - lo) / v)) < 1e-6


def test_pointpillars_trains_under_autocast(batch):
    """Mixed precision through a whole detector: PointPillars is pure torch (spconv's CPU kernels take
    no bfloat16, so the voxel detectors cannot run under CPU autocast). The loss under autocast stays
    close to the float32 loss and every parameter that gets a gradient in float32 gets a finite one."""
    torch.manual_seed(0)
    model = build_detector("pointpillars", TINY, num_fusion_blocks=2, fusion="msdff")

    def step(enabled: bool):
        model.zero_grad(set_to_none=True)
        torch.manual_seed(1)  # the same dropout / sampling, if any
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=enabled):
            total = sum(model(batch).values())
        total.float().backward()
        return float(total), {k: p.grad for k, p in model.named_parameters() if p.grad is not None}

    loss32, grads32 = step(False)
    loss16, grads16 = step(True)
    assert math.isfinite(loss16) and abs(loss16 - loss32) <= 0.05 * abs(loss32)
    assert grads16.keys() == grads32.keys() and any("fusions" in k for k in grads16)
    assert all(torch.isfinite(g).all() for g in grads16.values())


def test_msdff_blocks_use_the_paper_width_unless_told():
    # value_proj: FPN -> FPN channels, output_proj: FPN -> voxel channels (paper eq. 10, the authors' code);
    # msdff_value_dim="voxel_channels" gives the narrow layout, an int any width.
    from dataclasses import replace

    widths = {}
    for vd in (None, "voxel_channels", 4):
        model = build_detector("pointpillars", replace(TINY, msdff_value_dim=vd), num_fusion_blocks=2, fusion="msdff")
        widths[vd] = [(tuple(b.fusion.value_proj.weight.shape), tuple(b.fusion.output_proj.weight.shape))
                      for b in model.backbone.fusions]
    c, (v0, v1) = TINY.fpn_channels, TINY.pillar_filters[:2]
    assert widths[None] == [((c, c), (v0, c)), ((c, c), (v1, c))]
    assert widths["voxel_channels"] == [((v0, c), (v0, v0)), ((v1, c), (v1, v1))]
    assert widths[4] == [((4, c), (v0, 4)), ((4, c), (v1, 4))]
    with pytest.raises(MSSFError, match="msdff_value_dim"):
        build_detector("pointpillars", replace(TINY, msdff_value_dim="wide"), num_fusion_blocks=1, fusion="msdff")
