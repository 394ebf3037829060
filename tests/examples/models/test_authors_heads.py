"""The authors' detection heads and BEV blocks after conversion, against float64 re-implementations of
their definitions (``EricLiuhhh/MSSF`` @ 8341012, mmdet3d 1.x), written here with plain torch and loops:

* MSSF-PP ``Anchor3DHead``: 1x1 convolutions, ``permute(1, 2, 0).reshape(-1, K)`` flattening,
  ``AlignedAnchor3DRangeGenerator`` (one range per size, ``linspace`` + half-cell shift, ``(y, x, size,
  yaw)`` order), ``DeltaXYZWLHRBBoxCoder.decode`` (bottom ``z`` lifted by half the height) and the
  direction fix of ``_predict_by_feat_single`` (offset ``-pi / 2``, period ``pi``).
* MSSF-V ``VoxelNeXtHead`` / ``SeparateHeadVoxelNeXt``: submanifold 3x3 convolution with bias, BN1d,
  ReLU, 1x1 convolution per branch (spconv 2.3's 1x1 path); ``VoxelNeXtBBoxCoder.decode`` per voxel. The
  same branch built from spconv's own ``SubMConv2d`` gives the head's outputs (in float32, see the test).
* MSSF-PP ``SECONDFuse`` blocks and ``SECONDFPN`` deblocks (conv / BN(eps 1e-3) / ReLU, transposed conv).
* MSSF-V's BEV tail in ``SparseEncoderVoxelNeXtFuse``: ``bev_out``, ``conv_out``, ``shared_conv``.
"""

import math
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

pytest.importorskip("spconv")

from mssf_examples.models.authors_checkpoint import convert_authors, head_pairs  # noqa: E402
from mssf_examples.models.heads import AnchorHead, BEVGrid  # noqa: E402
from mssf_examples.models.heads.authors import (  # noqa: E402
    AuthorsVoxelNeXtHead,
    authors_anchor_head_kwargs,
    authors_anchor_z_centers,
)

sys.path.insert(0, str(Path(__file__).parent))
from test_authors_checkpoint import _bn, their_mssf_pp_shapes  # noqa: E402

F64 = torch.float64
OURS = ("Car", "Pedestrian", "Cyclist")  # the VoD preset's order
THEIRS = ("Pedestrian", "Cyclist", "Car")  # vod-3d-3class
SIZES = {"Pedestrian": (0.8, 0.6, 1.73), "Cyclist": (1.76, 0.6, 1.73), "Car": (3.9, 1.6, 1.56)}
BOTTOMS = {"Pedestrian": -0.6, "Cyclist": -0.6, "Car": -1.78}


def _random(shapes, seed):
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, v in shapes.items():
        if v == ():
            out[k] = torch.tensor(7)
        elif k.endswith("running_var"):
            out[k] = 0.5 + torch.rand(v, generator=g, dtype=F64)
        elif k.endswith(("norm.weight", ".1.weight", ".4.weight")) and len(v) == 1:
            out[k] = 1 + 0.3 * torch.randn(v, generator=g, dtype=F64)
        else:
            out[k] = 0.3 * torch.randn(v, generator=g, dtype=F64)
    return out


def _wrap(x):
    return torch.remainder(x + math.pi, 2 * math.pi) - math.pi


# ---------------------------------------------------------------------------------------------------
# Anchor3DHead
def their_anchors(ny, nx, x_range, y_range):
    """AlignedAnchor3DRangeGenerator(ranges one per size, rotations [0, 1.57], reshape_out=False), float64."""
    per_size = []
    for name in THEIRS:
        xs = torch.linspace(x_range[0], x_range[1], nx + 1, dtype=F64)
        ys = torch.linspace(y_range[0], y_range[1], ny + 1, dtype=F64)
        xs, ys = xs + (xs[1] - xs[0]) / 2, ys + (ys[1] - ys[0]) / 2
        a = torch.zeros(ny, nx, 2, 7, dtype=F64)
        for iy in range(ny):
            for ix in range(nx):
                for r, yaw in enumerate((0.0, 1.57)):
                    a[iy, ix, r] = torch.tensor([xs[ix], ys[iy], BOTTOMS[name], *SIZES[name], yaw], dtype=F64)
        per_size.append(a)
    return torch.stack(per_size, 2).reshape(-1, 7)  # (y, x, size, rotation)


def their_anchor_head(x, sd):
    """Their forward + _predict_by_feat_single's decoding (before NMS): scores (N, K), boxes (N, 7) bottom z."""
    def conv1x1(name):
        w, b = sd[f"bbox_head.{name}.weight"][:, :, 0, 0], sd[f"bbox_head.{name}.bias"]
        return torch.einsum("oc,chw->ohw", w, x[0]) + b[:, None, None]

    cls = conv1x1("conv_cls").permute(1, 2, 0).reshape(-1, 3)
    reg = conv1x1("conv_reg").permute(1, 2, 0).reshape(-1, 7)
    dirs = conv1x1("conv_dir_cls").permute(1, 2, 0).reshape(-1, 2).argmax(-1)
    anchors = their_anchors(x.shape[2], x.shape[3], (0.0, 51.2), (-25.6, 25.6))
    boxes = torch.zeros_like(reg)
    for i in range(len(reg)):
        xa, ya, za, wa, la, ha, ra = anchors[i].tolist()
        xt, yt, zt, wt, lt, ht, rt = reg[i].tolist()
        za = za + ha / 2
        diag = math.sqrt(la**2 + wa**2)
        hg = math.exp(ht) * ha
        yaw = rt + ra
        rot = (yaw - (-math.pi / 2)) - math.floor((yaw - (-math.pi / 2)) / math.pi + 0.0) * math.pi  # limit_period
        yaw = rot + (-math.pi / 2) + math.pi * float(dirs[i])
        boxes[i] = torch.tensor([xt * diag + xa, yt * diag + ya, zt * ha + za - hg / 2, math.exp(wt) * wa,
                                 math.exp(lt) * la, hg, yaw], dtype=F64)
    return torch.sigmoid(cls), boxes


def test_converted_anchor_head_equals_their_anchor3d_head_in_float64():
    ny, nx, c = 6, 5, 384
    grid = BEVGrid(0.0, -25.6, 51.2, 25.6, ny, nx)
    sizes = [SIZES[k] for k in OURS]
    head = AnchorHead(c, grid, sizes, authors_anchor_z_centers(OURS, sizes, "vod"), dtype=F64,
                      **authors_anchor_head_kwargs()).eval()
    shapes = {k: v for k, v in their_mssf_pp_shapes().items() if k.startswith("bbox_head.")}
    theirs = _random(shapes, 1)
    pairs = head_pairs(theirs, SimpleNamespace(preset=SimpleNamespace(class_names=OURS), head=head), "mssf_pp")
    assert sorted(pairs) == sorted(theirs)
    own = {o[len("head."):]: theirs[k] if fn is None else fn(theirs[k]) for k, (o, fn) in pairs.items()}
    head.load_state_dict(own, strict=True)
    x = 0.05 * torch.randn(1, c, ny, nx, generator=torch.Generator().manual_seed(2), dtype=F64)
    want_scores, want_boxes = their_anchor_head(x, theirs)
    with torch.no_grad():
        preds = head(x)
        boxes = head.decode_boxes(preds)[0]
        scores = torch.sigmoid(preds["cls"][0])
    perm = [THEIRS.index(k) for k in OURS]
    # our anchor (cell, class k, yaw r) is their anchor (cell, perm[k], r); our logit k' their perm[k']
    ours_rows = torch.arange(ny * nx * 6).reshape(ny * nx, 3, 2)
    their_rows = ours_rows.clone()
    for k in range(3):
        their_rows[:, k] = torch.arange(ny * nx)[:, None] * 6 + perm[k] * 2 + torch.arange(2)
    o, t = ours_rows.flatten(), their_rows.flatten()
    assert (scores[o] - want_scores[t][:, perm]).abs().max() <= 1e-9
    centre = want_boxes[t].clone()
    centre[:, 2] += centre[:, 5] / 2  # theirs bottom z, ours centre z
    assert (boxes[o, :6] - centre[:, :6]).abs().max() <= 1e-9
    assert _wrap(boxes[o, 6] - centre[:, 6]).abs().max() <= 1e-9
    # without the permutation (their class order read as ours) the scores differ
    assert (scores[o] - want_scores[o]).abs().max() > 1e-2


# ---------------------------------------------------------------------------------------------------
# VoxelNeXtHead
BRANCHES = (("reg", 2), ("height", 1), ("dim", 3), ("rot", 2), ("heatmap", 3))


def their_voxelnext_branch(feats, coords, sd, prefix):
    """SubMConv2d 3x3 (bias) -> BN1d (eval) -> ReLU -> SubMConv2d 1x1 (bias), loops over the voxels."""
    where = {tuple(c): i for i, c in enumerate(coords.tolist())}
    w, b = sd[f"{prefix}.0.0.weight"], sd[f"{prefix}.0.0.bias"]  # (out, kh, kw, in)
    hidden = torch.zeros(len(feats), w.shape[0], dtype=F64)
    for i, (bi, y, x) in enumerate(coords.tolist()):
        acc = b.clone()
        for dy in range(3):
            for dx in range(3):
                j = where.get((bi, y + dy - 1, x + dx - 1))
                if j is not None:
                    acc = acc + w[:, dy, dx, :] @ feats[j]
        hidden[i] = acc
    bn = {k: sd[f"{prefix}.0.1.{k}"] for k in ("weight", "bias", "running_mean", "running_var")}
    hidden = torch.relu((hidden - bn["running_mean"]) / torch.sqrt(bn["running_var"] + 1e-5) * bn["weight"] + bn["bias"])
    # spconv 2.3's SubMConv2d with a 1x1 kernel is torch.mm(x, weight.view(in, out)) (conv.py, FILTER_HWIO
    # False): their (out, 1, 1, in) tensor read as (in, out), what their trained head computes
    w1 = sd[f"{prefix}.1.weight"]
    return hidden @ w1.reshape(w1.shape[3], w1.shape[0]) + sd[f"{prefix}.1.bias"]


def test_converted_voxelnext_head_equals_their_voxelnext_head_in_float64():
    g = torch.Generator().manual_seed(3)
    c, ny, nx = 16, 12, 10
    grid = BEVGrid(0.0, -25.6, 51.2, 25.6, ny, nx)  # (cells of 5.12 m: the coder's factor x voxel size)
    cells = torch.randperm(2 * ny * nx, generator=g)[:70]
    coords = torch.stack([cells // (ny * nx), (cells % (ny * nx)) // nx, cells % nx], 1).int()
    feats = torch.randn(len(coords), c, generator=g, dtype=F64)
    shapes = {}
    for branch, out in BRANCHES:
        p = f"pts_bbox_head.task_heads.0.{branch}"
        shapes.update({f"{p}.0.0.weight": (c, 3, 3, c), f"{p}.0.0.bias": (c,), f"{p}.1.weight": (out, 1, 1, c),
                       f"{p}.1.bias": (out,)})
        shapes.update(_bn(f"{p}.0.1", c))
    theirs = _random(shapes, 4)
    head = AuthorsVoxelNeXtHead(c, grid, 3, head_channels=c, dtype=F64).eval()
    pairs = head_pairs(theirs, SimpleNamespace(preset=SimpleNamespace(class_names=OURS), head=head), "mssf_v")
    assert sorted(pairs) == sorted(theirs)
    head.load_state_dict({o[len("head."):]: theirs[k] if fn is None else fn(theirs[k])
                          for k, (o, fn) in pairs.items()}, strict=True)
    with torch.no_grad():
        preds = head(feats, coords, 2)
    want = {b: their_voxelnext_branch(feats, coords, theirs, f"pts_bbox_head.task_heads.0.{b}") for b, _ in BRANCHES}
    perm = [THEIRS.index(k) for k in OURS]
    assert (preds["hm"] - want["heatmap"][:, perm]).abs().max() <= 1e-9
    for b, ours in (("reg", "center"), ("height", "center_z"), ("dim", "dim"), ("rot", "rot")):
        assert (preds[ours] - want[b]).abs().max() <= 1e-9, b
    # their VoxelNeXtBBoxCoder.decode per voxel (x from the voxel's integer index + reg, no half cell),
    # then the head's z - h / 2 (bottom); ours keeps the centre
    from mssf_examples.models.ops.boxes import decode_center

    ours_boxes = decode_center(head._codes(preds), coords[:, [2, 1]].long(), (grid.cell_x, grid.cell_y),
                               (grid.x_min, grid.y_min))
    factor_voxel = (51.2 / nx, 51.2 / ny)  # out_size_factor * voxel_size
    for i, (_, y, x) in enumerate(coords.tolist()):
        dims = torch.exp(want["dim"][i])
        box = [(x + want["reg"][i, 0]) * factor_voxel[0] + 0.0, (y + want["reg"][i, 1]) * factor_voxel[1] - 25.6,
               want["height"][i, 0] - dims[2] / 2, *dims, torch.atan2(want["rot"][i, 0], want["rot"][i, 1])]
        box = torch.stack([torch.as_tensor(v, dtype=F64) for v in box])
        box[2] += box[5] / 2
        assert (ours_boxes[i] - box).abs().max() <= 1e-9


# ---------------------------------------------------------------------------------------------------
# SECONDFuse blocks and SECONDFPN deblocks of MSSF-PP
def their_block(x, sd, i, n, stride):
    def bn(h, p):
        return (h - sd[f"{p}.running_mean"][:, None, None]) / torch.sqrt(sd[f"{p}.running_var"][:, None, None] + 1e-3) \
            * sd[f"{p}.weight"][:, None, None] + sd[f"{p}.bias"][:, None, None]

    h = torch.relu(bn(F.conv2d(x, sd[f"backbone.blocks.{i}.0.weight"], stride=stride, padding=1), f"backbone.blocks.{i}.1"))
    for j in range(n):
        h = torch.relu(bn(F.conv2d(h, sd[f"backbone.blocks.{i}.{3 + 3 * j}.weight"], padding=1),
                          f"backbone.blocks.{i}.{4 + 3 * j}"))
    return h


def their_deblock(x, sd, i, k):
    p = f"neck.deblocks.{i}"
    h = F.conv_transpose2d(x, sd[f"{p}.0.weight"], stride=k)
    h = (h - sd[f"{p}.1.running_mean"][:, None, None]) / torch.sqrt(sd[f"{p}.1.running_var"][:, None, None] + 1e-3) \
        * sd[f"{p}.1.weight"][:, None, None] + sd[f"{p}.1.bias"][:, None, None]
    return torch.relu(h)


def test_converted_second_blocks_and_fpn_deblocks_equal_theirs_in_float64():
    from mssf_examples.models.backbones import AuthorsPointPillarsBackbone
    from mssf_examples.models.voxelize import VoxelGrid

    model = AuthorsPointPillarsBackbone(7, VoxelGrid(voxel_size=(0.16, 0.16, 5.0), point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0)), [256] * 5)
    theirs = _random(their_mssf_pp_shapes(), 5)
    sd, report = convert_authors({k: v.float() if v.is_floating_point() else v for k, v in theirs.items()}, model)
    model.load_state_dict(sd, strict=True)
    model = model.double().eval()
    for k in [k for k in theirs if k.startswith(("backbone.blocks.", "neck.deblocks."))]:
        ours = k.replace("backbone.blocks.", "blocks.").replace("neck.deblocks.", "deblocks.")
        model.state_dict()[ours].copy_(theirs[k])  # float64 tensors (the conversion above ran in float32)
    g = torch.Generator().manual_seed(6)
    with torch.no_grad():
        for i, (cin, n, k) in enumerate(((128, 3, 1), (128, 5, 2), (128, 5, 4))):
            x = torch.randn(1, cin, 16, 16, generator=g, dtype=F64)
            want = their_block(x, theirs, i, n, 2)
            assert (model.blocks[i](x) - want).abs().max() <= 1e-9
            cup = want.shape[1] + (64 if i == 0 else 0)  # block 0's deblock reads the concatenated fused BEV
            y = torch.randn(1, cup, 8, 8, generator=g, dtype=F64)
            assert (model.deblocks[i](y) - their_deblock(y, theirs, i, k)).abs().max() <= 1e-9


def test_authors_voxelnext_head_equals_the_same_branches_built_from_spconv():
    """The spconv-free convolutions against spconv's SubMConv2d (the framework their head runs on), float32.

    (float32: spconv 2.3.8's CPU SubMConv2d / SubMConv3d in float64 gave wrong results with two torch threads,
    in 21 of 30 random draws up to 1.07 on unit-scale features, while float32, and float64 on one thread,
    matched a loop; this head does not depend on it.)"""
    import spconv.pytorch as spconv

    g = torch.Generator().manual_seed(7)
    c, ny, nx = 16, 12, 10
    cells = torch.randperm(2 * ny * nx, generator=g)[:80]
    coords = torch.stack([cells // (ny * nx), (cells % (ny * nx)) // nx, cells % nx], 1).int()
    feats = torch.randn(len(coords), c, generator=g)
    head = AuthorsVoxelNeXtHead(c, BEVGrid(0.0, -25.6, 51.2, 25.6, ny, nx), 3, head_channels=c).eval()
    for p in head.parameters():
        torch.nn.init.normal_(p, std=0.3, generator=g)
    with torch.no_grad():
        ours = head(feats, coords, 2)
    for name, branch in head.heads.items():
        conv3, bn, _ = branch[0]
        ref = spconv.SparseSequential(
            spconv.SubMConv2d(c, c, 3, padding=1, bias=True, indice_key=f"t_{name}"), torch.nn.BatchNorm1d(c),
            torch.nn.ReLU(), spconv.SubMConv2d(c, branch[1].out_channels, 1, bias=True, indice_key=f"t1_{name}"))
        ref.load_state_dict({"0.weight": conv3.weight, "0.bias": conv3.bias, **{f"1.{k}": v for k, v in bn.state_dict().items()},
                             "3.weight": branch[1].weight, "3.bias": branch[1].bias})
        ref.train()  # (spconv's CPU inference kernel refuses a bias) with the norm in eval mode
        ref[1].eval()
        with torch.no_grad():
            out = ref(spconv.SparseConvTensor(feats, coords, [ny, nx], 2))
        assert torch.equal(out.indices, coords)
        assert (out.features - ours[name]).abs().max() <= 1e-4 * (1 + ours[name].abs().max()), name
    # the 1x1 layer read as a transpose (x @ W[:, 0, 0, :].T) would differ
    w = head.heads["hm"][1].weight
    assert not torch.allclose(w.reshape(c, 3), w[:, 0, 0, :].T)


def test_authors_layout_feeds_the_image_branch_their_normalised_images():
    from test_detectors import make_batch

    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.presets import TINY

    torch.manual_seed(0)
    model = build_detector("voxelnext", TINY, num_fusion_blocks=2, layout="authors").eval()
    seen, forward = [], model.image_branch.forward
    model.image_branch.forward = lambda x: seen.append(x) or forward(x)
    batch = make_batch()
    with torch.no_grad():
        model(batch)
    mean, std = (123.675, 116.28, 103.53), (58.395, 57.12, 57.375)  # their data_preprocessor (RGB)
    for c in range(3):
        want = (batch.images[:, :, c] * 255 - mean[c]) / std[c]
        assert (seen[0][:, :, c] - want).abs().max() <= 1e-5


# ---------------------------------------------------------------------------------------------------
# SparseEncoderVoxelNeXtFuse's BEV tail: bev_out (sum of x_conv4..6 at equal (b, y, x), x_conv5 / x_conv6
# indices x2 / x4), conv_out (regular SparseConv2d 3x3, BN1d eps 1e-3, ReLU), shared_conv (SubMConv2d 3x3
# with bias, BN1d eps 1e-5, ReLU)
def their_sparse_conv2d(sites, w, b, ny, nx, subm):
    """Loops: output sites = the input sites (submanifold) or every in-bounds cell with an input in its
    3x3 window (regular, padding 1); value = sum over the window of weight[:, dy, dx, :] @ input."""
    if subm:
        outs = sorted(sites)
    else:
        outs = sorted({(bi, y + dy, x + dx) for (bi, y, x) in sites for dy in (-1, 0, 1) for dx in (-1, 0, 1)
                       if 0 <= y + dy < ny and 0 <= x + dx < nx})
    res = {}
    for (bi, y, x) in outs:
        acc = torch.zeros(w.shape[0], dtype=F64) if b is None else b.clone()
        for dy in range(3):
            for dx in range(3):
                f = sites.get((bi, y + dy - 1, x + dx - 1))
                if f is not None:
                    acc = acc + w[:, dy, dx, :] @ f
        res[(bi, y, x)] = acc
    return res


@pytest.mark.usefixtures("one_thread")  # spconv's float64 CPU kernels are right on one thread only
def test_voxelnext_bev_tail_in_their_layout_equals_theirs_in_float64():
    from mssf_examples.models.backbones import BackboneOutput, VoxelNeXtBackbone
    from mssf_examples.models.voxelize import VoxelGrid

    g = torch.Generator().manual_seed(8)
    c = 8
    grid = VoxelGrid(voxel_size=(0.2, 0.2, 0.125), point_cloud_range=(0.0, -6.4, -3.0, 12.8, 6.4, 2.0))  # 64 x 64, BEV 8 x 8 at stride 8
    model = VoxelNeXtBackbone(7, grid, channels=(c,) * 7, out_channels=c, authors_layout=True, num_fusion_blocks=0)
    model = model.double().train()
    for m in (model.conv_out[1], model.shared_conv[1]):
        m.eval()
        m.running_mean.copy_(0.2 * torch.randn(c, generator=g, dtype=F64))
        m.running_var.copy_(0.5 + torch.rand(c, generator=g, dtype=F64))
        m.weight.data.copy_(1 + 0.2 * torch.randn(c, generator=g, dtype=F64))
        m.bias.data.copy_(0.2 * torch.randn(c, generator=g, dtype=F64))
    ny, nx = model.bev_shape

    def stage(n, factor):
        cells = torch.randperm(2 * (ny // factor) * (nx // factor), generator=g)[:n]
        per = (ny // factor) * (nx // factor)
        b, y, x = cells // per, (cells % per) // (nx // factor), cells % (nx // factor)
        z = torch.randint(0, 3, (n,), generator=g)
        return SimpleNamespace(features=torch.randn(n, c, generator=g, dtype=F64),
                               coords=torch.stack([b, z, y, x], 1).int())

    stages = [stage(20, 1), stage(8, 2), stage(3, 4)]
    model.forward_stages = lambda voxels, inputs: BackboneOutput(stages=[None, None, None] + stages)
    with torch.no_grad():
        feats, coords = model(SimpleNamespace(batch_size=2), None).sparse_bev
    # theirs: bev_out, then the two layers
    merged = {}
    for s, k in zip(stages, (1, 2, 4)):
        for f, (bi, _, y, x) in zip(s.features, s.coords.tolist()):
            key = (bi, y * k, x * k)
            merged[key] = merged.get(key, torch.zeros(c, dtype=F64)) + f
    sd = {k: v.detach() for k, v in model.state_dict().items()}

    def bn_relu(v, p, eps):
        return torch.relu((v - sd[f"{p}.running_mean"]) / torch.sqrt(sd[f"{p}.running_var"] + eps) * sd[f"{p}.weight"]
                          + sd[f"{p}.bias"])

    out = their_sparse_conv2d(merged, sd["conv_out.0.weight"], None, ny, nx, subm=False)
    out = {k: bn_relu(v, "conv_out.1", 1e-3) for k, v in out.items()}
    out = their_sparse_conv2d(out, sd["shared_conv.0.weight"], sd["shared_conv.0.bias"], ny, nx, subm=True)
    out = {k: bn_relu(v, "shared_conv.1", 1e-5) for k, v in out.items()}
    have = {tuple(k): f for k, f in zip(coords.tolist(), feats)}
    assert have.keys() == out.keys() and len(out) > len(merged)  # the regular conv dilates the set
    assert max((have[k] - out[k]).abs().max().item() for k in out) <= 1e-9


def test_authors_helpers_name_bad_arguments():
    from mssf_blocks.errors import MSSFError
    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.heads.authors import class_permutation
    from mssf_examples.models.presets import TINY

    assert class_permutation(OURS) == (2, 0, 1)
    assert class_permutation(("Car", "Pedestrian", "Cyclist", "Truck")) == (2, 0, 1, 3)
    with pytest.raises(MSSFError, match=r"class names: expected the classes .*got \('Car', 'Bus'"):
        class_permutation(("Car", "Bus", "Cyclist"))
    assert authors_anchor_z_centers(OURS, [SIZES[k] for k in OURS], "vod") == pytest.approx((-1.0, 0.265, 0.265))
    with pytest.raises(MSSFError, match="dataset: expected one of"):
        authors_anchor_z_centers(OURS, [SIZES[k] for k in OURS], "kitti")
    with pytest.raises(MSSFError, match="layout: 'authors' exists for"):
        build_detector("second", TINY, layout="authors")
    with pytest.raises(MSSFError, match="layout: expected 'paper' or 'authors'"):
        build_detector("voxelnext", TINY, layout="theirs")
