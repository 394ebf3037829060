"""Whole-checkpoint import of the authors' MSSF-PP (``EricLiuhhh/MSSF``) into the example models.

Their tensor names and shapes are written out below from their config
(``pointpillars_hv_secfpn_8xb6-160e_vod-3d-3class_mm_bb_bevfeat_lr0001`` on
``pointpillars_hv_secfpn_vod_mm_backbone``) and source (``VoxelNetFuse``, ``PillarFeatureNet``,
``PointPillarsScatterFuse``, ``SECONDFuse``, ``SECONDFPN``, ``Anchor3DHead``, mmdet's ResNet-50 and FPN);
no download. Random tensors under those names go through the converter and must load with
``strict=True``.
"""

import pytest
import torch

pytest.importorskip("spconv")

from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_examples.models.authors_checkpoint import convert_authors  # noqa: E402
from mssf_examples.models.backbones import AuthorsPointPillarsBackbone  # noqa: E402
from mssf_examples.models.voxelize import VoxelGrid  # noqa: E402

VOD_PILLARS = VoxelGrid(voxel_size=(0.16, 0.16, 5.0), point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0))


def _bn(p, c):
    return {f"{p}.weight": (c,), f"{p}.bias": (c,), f"{p}.running_mean": (c,), f"{p}.running_var": (c,),
            f"{p}.num_batches_tracked": ()}


def their_mssf_pp_shapes():
    s = {"voxel_encoder.pfn_layers.0.linear.weight": (64, 7 + 3 + 3)}  # points, cluster offset, centre offset
    s.update(_bn("voxel_encoder.pfn_layers.0.norm", 64))
    for enc in ("middle_encoder", "backbone"):
        s[f"{enc}.conv_input.0.weight"] = (64, 3, 3, 3, 7)  # SubMConv3d 7 -> 64, spconv 2 layout
        att = f"{enc}.fusion_blocks.x_conv1.img_cross_att.deformable_attention"
        for name, (o, i) in {"sampling_offsets": (8 * 5 * 4 * 2, 64), "attention_weights": (8 * 5 * 4, 64),
                             "value_proj": (256, 256), "output_proj": (64, 256)}.items():
            s[f"{att}.{name}.weight"], s[f"{att}.{name}.bias"] = (o, i), (o,)
        s[f"{enc}.query_proj.0.weight"], s[f"{enc}.query_proj.0.bias"] = (64, 256 + 64 + 3), (64,)
        s.update(_bn(f"{enc}.query_proj.1", 64))
        s[f"{enc}.voxel_fuse.img_transform.0.weight"], s[f"{enc}.voxel_fuse.img_transform.0.bias"] = (256, 256), (256,)
        s.update(_bn(f"{enc}.voxel_fuse.img_transform.1", 256))
        seg = f"{enc}.seg_heads.x_conv1.seg_cls_layer"
        s[f"{seg}.0.weight"], s[f"{seg}.3.weight"] = (256, 64), (256, 256)
        s.update(_bn(f"{seg}.1", 256))
        s.update(_bn(f"{seg}.4", 256))
        s[f"{seg}.6.weight"], s[f"{seg}.6.bias"] = (1, 256), (1,)
    s["backbone.height_embeddings.weight"] = (41, 64)
    for i, (cin, cout, n) in enumerate(((128, 64, 3), (128, 128, 5), (128, 256, 5))):
        s[f"backbone.blocks.{i}.0.weight"] = (cout, cin, 3, 3)
        s.update(_bn(f"backbone.blocks.{i}.1", cout))
        for j in range(n):
            s[f"backbone.blocks.{i}.{3 + 3 * j}.weight"] = (cout, cout, 3, 3)
            s.update(_bn(f"backbone.blocks.{i}.{4 + 3 * j}", cout))
    for i, (cin, k) in enumerate(((128, 1), (128, 2), (256, 4))):
        s[f"neck.deblocks.{i}.0.weight"] = (cin, 128, k, k)  # ConvTranspose2d: (in, out, k, k)
        s.update(_bn(f"neck.deblocks.{i}.1", 128))
    for name, o in (("conv_cls", 3 * 2 * 3), ("conv_reg", 3 * 2 * 7), ("conv_dir_cls", 3 * 2 * 2)):
        s[f"bbox_head.{name}.weight"], s[f"bbox_head.{name}.bias"] = (o, 384, 1, 1), (o,)
    s["img_backbone.conv1.weight"] = (64, 3, 7, 7)
    s.update(_bn("img_backbone.bn1", 64))
    cin = 64
    for layer, (n, planes) in enumerate(zip((3, 4, 6, 3), (64, 128, 256, 512)), 1):
        for b in range(n):
            p = f"img_backbone.layer{layer}.{b}"
            for c, shape in ((1, (planes, cin, 1, 1)), (2, (planes, planes, 3, 3)), (3, (4 * planes, planes, 1, 1))):
                s[f"{p}.conv{c}.weight"] = shape
                s.update(_bn(f"{p}.bn{c}", shape[0]))
            if b == 0:
                s[f"{p}.downsample.0.weight"] = (4 * planes, cin, 1, 1)
                s.update(_bn(f"{p}.downsample.1", 4 * planes))
            cin = 4 * planes
    for i, c in enumerate((256, 512, 1024, 2048)):
        s[f"img_neck.lateral_convs.{i}.conv.weight"], s[f"img_neck.lateral_convs.{i}.conv.bias"] = (256, c, 1, 1), (256,)
        s[f"img_neck.fpn_convs.{i}.conv.weight"], s[f"img_neck.fpn_convs.{i}.conv.bias"] = (256, 256, 3, 3), (256,)
    return s


def random_checkpoint(shapes, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {"meta": {}, "state_dict": {k: torch.tensor(5) if v == () else torch.randn(v, generator=g)
                                       for k, v in shapes.items()}}


def test_their_mssf_pp_checkpoint_loads_strictly_into_the_authors_layout():
    model = AuthorsPointPillarsBackbone(7, VOD_PILLARS, [256] * 5)
    ckpt = random_checkpoint(their_mssf_pp_shapes())
    theirs = ckpt["state_dict"]
    sd, report = convert_authors(ckpt, model)
    model.load_state_dict(sd, strict=True)
    assert report.missing == []
    assert len(report.mapped) + len(report.ignored) == len(theirs)
    assert {k.split(".")[0] for k, _ in report.ignored} == {"img_backbone", "img_neck", "bbox_head", "middle_encoder",
                                                           "backbone"}
    assert all("voxel_fuse.img_transform" in k for k, _ in report.ignored if k.startswith(("middle", "backbone")))
    own = model.state_dict()
    for k, ours, shape in report.mapped:
        assert tuple(own[ours].shape) == shape
        if "query_proj.0.weight" not in k and "pfn_layers.0.linear" not in k:
            assert torch.equal(own[ours], theirs[k]), k
    # the query-init columns: theirs [img | voxel | pos], ours [voxel | img | pos]
    w = theirs["backbone.query_proj.0.weight"]
    assert torch.equal(own["backbone_stage.block.query_init.linear.weight"], torch.cat([w[:, 256:320], w[:, :256], w[:, 320:]], 1))
    assert report.summary().startswith(f"mapped {len(report.mapped)}, ignored {len(report.ignored)}, missing 0")


def test_unknown_and_misshapen_tensors_raise_naming_them():
    model = AuthorsPointPillarsBackbone(7, VOD_PILLARS, [256] * 5)
    shapes = their_mssf_pp_shapes()
    extra = random_checkpoint({**shapes, "pts_fusion_layer.weight": (3,)})
    with pytest.raises(MSSFError, match=r"pts_fusion_layer\.weight"):
        convert_authors(extra, model)
    bad = random_checkpoint({**shapes, "backbone.blocks.1.0.weight": (128, 64, 3, 3)})
    with pytest.raises(MSSFError, match=r"backbone\.blocks\.1\.0\.weight has shape \(128, 64, 3, 3\)"):
        convert_authors(bad, model)
    with pytest.raises(MSSFError, match="layout"):
        convert_authors(extra, model, layout="mssf_v")


def test_example_detector_in_the_authors_mssf_pp_layout_trains_and_detects():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_detectors import make_batch

    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.presets import TINY

    torch.manual_seed(0)
    batch = make_batch()
    model = build_detector("pointpillars", TINY, num_fusion_blocks=2, pillar_layout="authors", score_threshold=0.0,
                           max_detections=10)
    assert isinstance(model.backbone, AuthorsPointPillarsBackbone) and model.backbone.bev_channels == 384
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    for _ in range(2):
        losses = model(batch)
        assert "seg" in losses and all(torch.isfinite(v) for v in losses.values())
        opt.zero_grad()
        losses["loss"].backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        dets = model(batch)
    assert len(dets) == 2 and all(d["boxes"].shape[1] == 7 for d in dets)
    with pytest.raises(MSSFError, match="pillar_layout"):
        build_detector("pointpillars", TINY, num_fusion_blocks=1, pillar_layout="authors")


def their_mssf_v_shapes():
    """``vx_mm_r50_ablation_n2m4`` on ``voxelnext_voxel005_vod_multimodal_r50pytorch``: fusion at x_conv1 and
    x_conv2, the semantic head at x_conv2, encoder channels 32/64/128/256/256/256 (the paper's doubled)."""
    e = "pts_middle_encoder"
    s = {f"{e}.conv_input.0.weight": (32, 3, 3, 3, 7)}
    s.update(_bn(f"{e}.conv_input.1", 32))

    def basic(p, c):
        for i in (1, 2):
            s[f"{p}.conv{i}.weight"] = (c, 3, 3, 3, c)
            s.update(_bn(f"{p}.bn{i}", c))

    chans = (32, 64, 128, 256, 256, 256)
    basic(f"{e}.conv1.0", 32)
    basic(f"{e}.conv1.1", 32)
    for i in range(2, 7):
        s[f"{e}.conv{i}.0.0.weight"] = (chans[i - 1], 3, 3, 3, chans[i - 2])
        s.update(_bn(f"{e}.conv{i}.0.1", chans[i - 1]))
        basic(f"{e}.conv{i}.1", chans[i - 1])
        basic(f"{e}.conv{i}.2", chans[i - 1])
    s[f"{e}.conv_out.0.weight"] = (256, 3, 3, 256)  # SparseConv2d, spconv 2 layout (out, kh, kw, in)
    s.update(_bn(f"{e}.conv_out.1", 256))
    s[f"{e}.shared_conv.0.weight"], s[f"{e}.shared_conv.0.bias"] = (256, 3, 3, 256), (256,)
    s.update(_bn(f"{e}.shared_conv.1", 256))
    for loc, c in (("x_conv1", 32), ("x_conv2", 64)):
        att = f"{e}.fusion_blocks.{loc}.img_cross_att.deformable_attention"
        for name, (o, i) in {"sampling_offsets": (8 * 5 * 4 * 2, c), "attention_weights": (8 * 5 * 4, c),
                             "value_proj": (256, 256), "output_proj": (c, 256)}.items():
            s[f"{att}.{name}.weight"], s[f"{att}.{name}.bias"] = (o, i), (o,)
    s[f"{e}.query_proj.0.weight"], s[f"{e}.query_proj.0.bias"] = (32, 256 + 32 + 3), (32,)
    s.update(_bn(f"{e}.query_proj.1", 32))
    s[f"{e}.voxel_fuse.img_transform.0.weight"], s[f"{e}.voxel_fuse.img_transform.0.bias"] = (256, 256), (256,)
    s.update(_bn(f"{e}.voxel_fuse.img_transform.1", 256))
    seg = f"{e}.seg_heads.x_conv2.seg_cls_layer"
    s[f"{seg}.0.weight"], s[f"{seg}.3.weight"], s[f"{seg}.6.weight"], s[f"{seg}.6.bias"] = (256, 64), (256, 256), (1, 256), (1,)
    s.update(_bn(f"{seg}.1", 256))
    s.update(_bn(f"{seg}.4", 256))
    # VoxelNeXtHead, one task of 3 classes: SeparateHeadVoxelNeXt branches (SubMConv2d 3x3 with bias, BN1d,
    # ReLU; SubMConv2d 1x1 with bias), share_conv_channel 256
    for branch, out in (("reg", 2), ("height", 1), ("dim", 3), ("rot", 2), ("heatmap", 3)):
        p = f"pts_bbox_head.task_heads.0.{branch}"
        s[f"{p}.0.0.weight"], s[f"{p}.0.0.bias"] = (256, 3, 3, 256), (256,)
        s.update(_bn(f"{p}.0.1", 256))
        s[f"{p}.1.weight"], s[f"{p}.1.bias"] = (out, 1, 1, 256), (out,)
    pp = their_mssf_pp_shapes()
    s.update({k: v for k, v in pp.items() if k.startswith(("img_backbone.", "img_neck."))})
    return s


def test_their_mssf_v_checkpoint_loads_strictly_into_voxelnext_in_their_layout():
    from mssf_examples.models.backbones import VoxelNeXtBackbone

    grid = VoxelGrid(voxel_size=(0.05, 0.05, 0.125), point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0))
    model = VoxelNeXtBackbone(7, grid, authors_layout=True, num_fusion_blocks=2, image_channels=[256] * 5)
    assert model.input_shape == (41, 1024, 1024)
    ckpt = random_checkpoint(their_mssf_v_shapes(), seed=2)
    theirs = ckpt["state_dict"]
    sd, report = convert_authors(ckpt, model, layout="mssf_v", stage_channels=32)
    model.load_state_dict(sd, strict=True)
    assert report.missing == [] and len(report.mapped) + len(report.ignored) == len(theirs)
    pairs = {k: ours for k, ours, _ in report.mapped}
    assert pairs["pts_middle_encoder.conv1.1.bn2.running_var"] == "stages.0.blocks.1.bn2.running_var"
    assert pairs["pts_middle_encoder.conv4.0.0.weight"] == "stages.3.downsample.0.weight"
    assert pairs["pts_middle_encoder.conv4.2.conv1.weight"] == "stages.3.blocks.1.conv1.weight"
    assert pairs["pts_middle_encoder.seg_heads.x_conv2.seg_cls_layer.6.bias"] == "stages.1.semantic_head.classifier.bias"
    own = model.state_dict()
    assert all(torch.equal(own[o], theirs[k]) for k, o in pairs.items() if "query_proj.0.weight" not in k)
    assert model.stages[1].head_position == "after_fusion" and model.stages[0].fusion.add_query


def test_voxelnext_in_their_layout_runs_its_regular_conv_out_and_shared_conv():
    from mssf_blocks.samplers import FusionInputs
    from mssf_examples.models.backbones import VoxelNeXtBackbone
    from mssf_examples.models.voxelize import DynamicVoxelizer

    grid = VoxelGrid(voxel_size=(0.4, 0.4, 0.125), point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0))
    kw = dict(channels=(8,) * 7, out_channels=8, num_fusion_blocks=2, image_channels=[16] * 3, msdff_heads=2,
              msdff_points=2, seg_hidden=(8,))
    torch.manual_seed(0)
    pts = torch.rand(60, 7) * torch.tensor([51.2, 51.2, 5, 1, 1, 1, 1]) - torch.tensor([0, 25.6, 3, 0, 0, 0, 0])
    pb = torch.randint(0, 2, (60,))
    cam = torch.tensor([[20.0, -30, 0, 0], [12, 0, -30, 0], [1, 0, 0, 0]]).expand(2, 3, 4).contiguous()
    inputs = FusionInputs([torch.randn(2, 16, 24 // s, 40 // s) for s in (4, 8, 16)], cam, (24, 40), pts[:, :3], pb)
    vox = DynamicVoxelizer(grid.point_cloud_range, grid.voxel_size)(pts, pb, 2)
    theirs = VoxelNeXtBackbone(7, grid, authors_layout=True, **kw).eval()
    ours = VoxelNeXtBackbone(7, grid, **kw).eval()
    a, b = theirs(vox, inputs).sparse_bev, ours(vox, inputs).sparse_bev
    # the regular conv_out dilates the merged BEV set; the submanifold one keeps it
    cells = lambda c: {tuple(r) for r in c.tolist()}  # noqa: E731
    assert cells(b[1]) < cells(a[1]) and a[0].shape[1] == 8


def test_their_mssf_pp_checkpoint_into_the_example_detector_maps_the_image_branch_too():
    import dataclasses

    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.presets import VOD

    preset = dataclasses.replace(VOD, num_image_levels=5)  # their FPN: five outputs, all fused
    model = build_detector("pointpillars", preset, num_fusion_blocks=2, pillar_layout="authors")
    ckpt = random_checkpoint(their_mssf_pp_shapes(), seed=4)
    theirs = ckpt["state_dict"]
    sd, report = convert_authors(ckpt, model)
    assert {k.split(".")[0] for k, _ in report.ignored} == {"bbox_head", "middle_encoder", "backbone"}
    assert report.missing and all(k.startswith("head.") for k in report.missing)
    result = model.load_state_dict(sd, strict=False)
    assert sorted(result.missing_keys) == sorted(report.missing) and result.unexpected_keys == []
    own = model.state_dict()
    assert torch.equal(own["image_branch.backbone.layer3.5.conv2.weight"], theirs["img_backbone.layer3.5.conv2.weight"])
    assert torch.equal(own["image_branch.neck.fpn_convs.3.conv.bias"], theirs["img_neck.fpn_convs.3.conv.bias"])
    assert torch.equal(own["backbone.blocks.1.0.weight"], theirs["backbone.blocks.1.0.weight"])


def their_pillar_features(points, coords_of, weight, bn, grid, max_points, training):
    """mmdet3d's PillarFeatureNet(legacy=True) + PointPillarsScatter, as their source reads, with loops:
    hard voxels padded to ``max_points`` rows, the pillar-centre offsets written into the points' xyz,
    padded rows zeroed, Linear (no bias), BN over every row (padded ones too), ReLU, max over the rows."""
    vx, vy, vz = grid.voxel_size
    x0, y0, z0 = grid.point_cloud_range[:3]
    pillars = {}
    for i, key in enumerate(coords_of):
        pillars.setdefault(key, []).append(i)
    rows, owner = [], []
    for n, (key, idx) in enumerate(sorted(pillars.items())):
        b, z, y, x = key
        pts = points[idx]
        mean = pts[:, :3].mean(0)
        centre = torch.tensor([x * vx + vx / 2 + x0, y * vy + vy / 2 + y0, z * vz + vz / 2 + z0], dtype=points.dtype)
        dec = torch.cat([pts[:, :3] - centre, pts[:, 3:], pts[:, :3] - mean, pts[:, :3] - centre], 1)
        dec = torch.cat([dec, dec.new_zeros(max_points - len(idx), dec.shape[1])])
        rows.append(dec)
        owner += [n] * max_points
    allrows = torch.cat(rows) @ weight.T
    if training:
        mu, var = allrows.mean(0), allrows.var(0, unbiased=False)
    else:
        mu, var = bn["running_mean"], bn["running_var"]
    h = torch.relu((allrows - mu) / torch.sqrt(var + 1e-3) * bn["weight"] + bn["bias"])
    feats = torch.stack([h[torch.tensor(owner) == n].max(0).values for n in range(len(pillars))])
    return dict(zip(sorted(pillars), feats))


@pytest.mark.parametrize("training", [False, True], ids=["eval", "train"])
def test_pfn_with_folded_weights_and_padding_equals_their_pillar_feature_net(training):
    from mssf_examples.models.voxelize import PillarFeatureNet

    g = torch.Generator().manual_seed(5)
    grid = VoxelGrid(voxel_size=(1.6, 1.6, 5.0), point_cloud_range=(0.0, -6.4, -3.0, 12.8, 6.4, 2.0))
    pts = torch.rand(120, 7, generator=g, dtype=torch.float64) * torch.tensor([12.8, 12.8, 5, 1, 1, 1, 1],
                                                                              dtype=torch.float64)
    pts[:, 1:3] -= torch.tensor([6.4, 3.0], dtype=torch.float64)
    pb = torch.randint(0, 2, (120,), generator=g)
    their_w = torch.randn(16, 13, generator=g, dtype=torch.float64)
    bn = {"weight": 1 + 0.2 * torch.randn(16, generator=g, dtype=torch.float64),
          "bias": 0.5 * torch.randn(16, generator=g, dtype=torch.float64),
          "running_mean": torch.randn(16, generator=g, dtype=torch.float64),
          "running_var": 0.5 + torch.rand(16, generator=g, dtype=torch.float64)}
    import functools

    norm = functools.partial(torch.nn.BatchNorm1d, eps=1e-3, momentum=0.01)  # mmdet3d's PFN norm
    pfn = PillarFeatureNet(7, 16, grid.point_cloud_range, (1.6, 1.6), dtype=torch.float64, max_points=32,
                           norm_layer=norm)
    from mssf_examples.models.authors_checkpoint import fold_legacy_pfn_columns

    pfn.linear.weight.data.copy_(fold_legacy_pfn_columns(their_w))
    for k, v in bn.items():
        getattr(pfn.norm, k).data.copy_(v)
    pfn.train(training)
    got = pfn(pts, pb, 2)
    cell = ((pts[:, :2] - torch.tensor([0.0, -6.4], dtype=torch.float64)) / 1.6).floor().long()
    coords_of = [(int(b), 0, int(c[1]), int(c[0])) for b, c in zip(pb, cell)]
    assert max(coords_of.count(c) for c in set(coords_of)) < 32
    want = their_pillar_features(pts, coords_of, their_w, bn, grid, 32, training)
    have = {tuple(int(v) for v in c): got.features[i] for i, c in enumerate(got.coords)}
    assert have.keys() == want.keys()
    assert max((have[k] - want[k]).abs().max().item() for k in want) <= 1e-9
    # without the padding the max differs (the padded rows win in some channels)
    pfn.max_points = None
    plain = pfn(pts, pb, 2)
    assert (plain.features - got.features).abs().max() > 1e-3
