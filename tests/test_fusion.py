"""Tests for ``mssf_blocks.fusion``: SFF, MSDFF, QueryInit, FusionInputs.

References are written here independently of the code under test: per-level ``F.grid_sample`` on
images projected pixel by pixel, naive loops over voxels/cameras/heads, hand-worked numbers.
"""

import math

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.fusion import MSDFF, SFF, FusionInputs, QueryInit, sample_at_projection
from mssf_blocks.geometry import CentroidProjection, VoxelCentroidProjector
from mssf_blocks.sparse import SparseVoxels
from mssf_blocks.testing import assert_close, gradcheck64

D64 = torch.float64
# MSDFF value widths: the paper's / authors' (value_dim = value_channels, the default) and the narrow
# layout (value_dim = embed_dim: the image projected down to the voxel width before the attention).
WIDTHS = [pytest.param("paper", id="paper_width"), pytest.param("narrow", id="narrow_width")]


def width_kw(width, embed_dim):
    """MSDFF keyword arguments of a value width of WIDTHS."""
    return {} if width == "paper" else {"value_dim": embed_dim}


# Tiny tensors: with 2 OpenMP threads on a loaded 2-core machine, each train-mode batch_norm call
# spins for ~10-50 ms (measured), which makes gradcheck 100x slower. One thread is plenty here.
pytestmark = pytest.mark.usefixtures("one_thread")


def make_projection(uv, valid, batch_index, device=None):
    n, v = valid.shape
    uv, valid, batch_index = (t.to(device) for t in (uv, valid, batch_index))
    return CentroidProjection(
        uv=uv, depth=torch.ones(n, v, dtype=uv.dtype, device=uv.device), valid=valid,
        centroid=torch.zeros(n, 3, dtype=uv.dtype, device=uv.device),
        has_points=torch.ones(n, dtype=torch.bool, device=uv.device), batch_index=batch_index,
    )


def randomize_norm(norm: nn.BatchNorm1d, gen):
    with torch.no_grad():
        c = norm.num_features
        norm.running_mean.copy_(torch.randn(c, generator=gen, dtype=D64))
        norm.running_var.copy_(torch.rand(c, generator=gen, dtype=D64) + 0.5)
        norm.weight.copy_(torch.randn(c, generator=gen, dtype=D64))
        norm.bias.copy_(torch.randn(c, generator=gen, dtype=D64))


def ref_bn_eval(x, norm):
    return (x - norm.running_mean) / torch.sqrt(norm.running_var + norm.eps) * norm.weight + norm.bias


def grid_sample_at(img, uv):
    """Independent bilinear reference: img (C, H, W), uv (K, 2) normalised -> (K, C)."""
    grid = (2.0 * uv - 1.0).view(1, 1, -1, 2)
    return F.grid_sample(img[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, :, 0].T


def scene(gen, b=2, v=2, n=7, chans=(3, 2), sizes=((5, 6), (3, 4))):
    """Random float64 levels (B, V, C, H, W), uv, valid mask (mixed), batch index."""
    levels = [torch.randn(b, v, c, h, w, generator=gen, dtype=D64) for c, (h, w) in zip(chans, sizes)]
    uv = torch.rand(n, v, 2, generator=gen, dtype=D64) * 0.9 + 0.05
    valid = torch.rand(n, v, generator=gen) > 0.3
    valid[0] = False  # seen by no camera
    valid[1] = True  # seen by all cameras
    if v > 1:
        valid[2] = torch.tensor([True] + [False] * (v - 1))
    batch_index = torch.randint(0, b, (n,), generator=gen)
    return levels, uv, valid, batch_index


# ---------------------------------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------------------------------
def reference_sff_sample(levels, uv, valid, batch_index):
    n, v = valid.shape
    out = torch.zeros(n, sum(l.shape[2] for l in levels), dtype=D64)
    for i in range(n):
        cams = [c for c in range(v) if valid[i, c]]
        for c in cams:
            row = [grid_sample_at(l[batch_index[i], c], uv[i, c][None])[0] for l in levels]
            out[i] += torch.cat(row) / len(cams)
    return out


def reference_msdff(mod: MSDFF, query, levels, uv, valid, batch_index):
    """Project every pixel with value_proj first, then per-level grid_sample (Deformable DETR's order)."""
    n, v = valid.shape
    e, m, lv, p = mod.value_dim, mod.num_heads, mod.num_levels, mod.num_points
    d = e // m
    off = (query @ mod.sampling_offsets.weight.T + mod.sampling_offsets.bias).view(n, m, lv, p, 2)
    att = (query @ mod.attention_weights.weight.T + mod.attention_weights.bias).view(n, m, lv * p)
    att = att.softmax(-1).view(n, m, lv, p)
    wv, bv = mod.value_proj.weight, mod.value_proj.bias
    projected = [torch.einsum("bvchw,ec->bvehw", l, wv) + bv[:, None, None] for l in levels]
    out = torch.zeros(n, e, dtype=D64)
    visible = valid.any(1)
    for i in range(n):
        cams = [c for c in range(v) if valid[i, c]]
        for c in cams:
            for h in range(m):
                for l in range(lv):
                    hl, wl = levels[l].shape[-2:]
                    loc = uv[i, c] + off[i, h, l] / torch.tensor([wl, hl], dtype=D64)
                    img = projected[l][batch_index[i], c, h * d:(h + 1) * d]
                    s = grid_sample_at(img, loc)  # (P, d)
                    out[i, h * d:(h + 1) * d] += (s * att[i, h, l][:, None]).sum(0) / len(cams)
    y = ref_bn_eval(out @ mod.output_proj.weight.T + mod.output_proj.bias, mod.norm)
    return torch.where(visible[:, None], y, torch.zeros_like(y)), off, att


def randomize_msdff(mod: MSDFF, gen, scale=0.5):
    with torch.no_grad():
        for lin in (mod.sampling_offsets, mod.attention_weights, mod.value_proj, mod.output_proj):
            lin.weight.copy_(torch.randn(lin.weight.shape, generator=gen, dtype=D64) * scale)
            lin.bias.copy_(torch.randn(lin.bias.shape, generator=gen, dtype=D64) * scale)
        mod.sampling_offsets.bias.mul_(4.0)  # offsets of a few pixels: some samples leave the image
    randomize_norm(mod.norm, gen)


# ---------------------------------------------------------------------------------------------------
# SFF
# ---------------------------------------------------------------------------------------------------
def test_sff_matches_reference(device):
    gen = torch.Generator().manual_seed(0)
    levels, uv, valid, bidx = scene(gen)
    sff = SFF([3, 2], 4, dtype=D64).eval()
    randomize_norm(sff.norm, gen)
    sampled = reference_sff_sample(levels, uv, valid, bidx)
    y = ref_bn_eval(sampled @ sff.linear.weight.T + sff.linear.bias, sff.norm)
    y[~valid.any(1)] = 0.0
    sff, proj, levels = sff.to(device), make_projection(uv, valid, bidx, device), [l.to(device) for l in levels]
    assert_close(sff.sample(levels, proj).cpu(), sampled)
    assert_close(sff(levels, proj).detach().cpu(), y)


def test_sff_gradcheck_train_mode():
    # Train-mode BN normalises with the statistics of the visible voxels of this very batch: a smooth,
    # deterministic function of the inputs (5 visible voxels), so gradcheck is valid; running-stat
    # updates between calls do not affect train-mode outputs.
    gen = torch.Generator().manual_seed(1)
    levels, uv, valid, bidx = scene(gen, n=6, chans=(2, 1), sizes=((3, 4), (2, 3)))
    sff = SFF([2, 1], 3, dtype=D64).train()
    assert int(valid.any(1).sum()) >= 3

    def fn(l0, l1, uv_):
        return sff([l0, l1], make_projection(uv_, valid, bidx))

    assert gradcheck64(fn, (levels[0], levels[1], uv))


def test_sff_pixel_hit_every_level():
    gen = torch.Generator().manual_seed(2)
    levels = [torch.randn(2, 1, 3, 8, 12, generator=gen, dtype=D64),
              torch.randn(2, 1, 5, 4, 6, generator=gen, dtype=D64)]
    sff = SFF([3, 5], 4, dtype=D64)
    for l, lvl in enumerate(levels):
        hl, wl = lvl.shape[-2:]
        cols = torch.tensor([0, 3, wl - 1])
        rows = torch.tensor([hl - 1, 1, 0])
        uv = torch.stack([(cols.to(D64) + 0.5) / wl, (rows.to(D64) + 0.5) / hl], -1)[:, None]
        bidx = torch.tensor([1, 0, 1])
        got = sff.sample(levels, make_projection(uv, torch.ones(3, 1, dtype=torch.bool), bidx))
        start = sum(x.shape[2] for x in levels[:l])
        want = lvl[bidx, 0, :, rows, cols]  # (3, C_l)
        assert_close(got[:, start:start + lvl.shape[2]], want)


def test_pixel_hit_through_projector():
    # lidar2img with depth 1, u = x, v = y: a point at x = 2 i + 0.5 lands on pixel centre i of the
    # stride-2 level ((u + 0.5) / W = (i + 0.5) / W_l), the centroid being the single point.
    gen = torch.Generator().manual_seed(3)
    img_h, img_w = 8, 16
    level = torch.randn(1, 6, img_h // 2, img_w // 2, generator=gen, dtype=D64)
    l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]], dtype=D64)
    i, j = 5, 2
    pts = torch.tensor([[2 * i + 0.5, 2 * j + 0.5, 0.5]], dtype=D64)
    vox = SparseVoxels(torch.zeros(1, 6, dtype=D64), torch.tensor([[0, 0, 2 * j, 2 * i]], dtype=torch.int32),
                       (1, img_h, img_w), 1, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    proj = VoxelCentroidProjector()(vox, pts, torch.zeros(1, dtype=torch.long), l2i, (img_h, img_w))
    assert_close(sample_at_projection(level, proj), level[0, :, j, i][None])


def test_invalid_points_give_zero_and_no_gradient():
    gen = torch.Generator().manual_seed(4)
    levels, uv, _, bidx = scene(gen)
    valid = torch.zeros(uv.shape[:2], dtype=torch.bool)  # uv inside the image, but every camera invalid
    levels = [l.requires_grad_(True) for l in levels]
    sff = SFF([3, 2], 4, dtype=D64).train()
    proj = make_projection(uv, valid, bidx)
    assert torch.equal(sff.sample(levels, proj), torch.zeros(7, 5, dtype=D64))
    out = sff(levels, proj)
    assert torch.equal(out, torch.zeros(7, 4, dtype=D64))
    (out.sum() + sff.sample(levels, proj).sum()).backward()
    for l in levels:
        assert l.grad is None or torch.count_nonzero(l.grad) == 0


def test_behind_camera_via_projector_is_zero():
    # depth = z: the voxel at z < 0 is behind the camera, the other one is in front but off-image.
    l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]], dtype=D64)
    coords = torch.tensor([[0, 0, 1, 1], [0, 3, 1, 50]], dtype=torch.int32)
    vox = SparseVoxels(torch.zeros(2, 2, dtype=D64), coords, (4, 4, 64), 1, (1.0, 1.0, 1.0), (0.0, 0.0, -2.0))
    proj = VoxelCentroidProjector()(vox, torch.zeros(0, 3, dtype=D64), torch.zeros(0, dtype=torch.long), l2i, (4, 4))
    assert not proj.valid.any()
    level = torch.randn(1, 2, 4, 4, dtype=D64, requires_grad=True)
    sff = SFF([2], 3, dtype=D64)
    out = sff([level], proj)
    assert torch.equal(sff.sample([level], proj), torch.zeros(2, 2, dtype=D64))
    assert torch.equal(out, torch.zeros(2, 3, dtype=D64))


@pytest.mark.parametrize("kind", ["sff", "msdff"])
def test_empty_and_batch_without_voxels(kind):
    gen = torch.Generator().manual_seed(5)
    levels = [torch.randn(2, 1, 4, 5, 6, generator=gen, dtype=D64, requires_grad=True),
              torch.randn(2, 1, 4, 3, 3, generator=gen, dtype=D64, requires_grad=True)]
    if kind == "sff":
        mod = SFF([4, 4], 8, dtype=D64)
    else:
        mod = MSDFF(8, 4, value_dim=6, num_heads=2, num_levels=2, num_points=2, dtype=D64)
    mod.train()

    def run(n, bidx):
        uv = torch.rand(n, 1, 2, generator=gen, dtype=D64)
        proj = make_projection(uv, torch.ones(n, 1, dtype=torch.bool), bidx)
        q = torch.randn(n, 8, dtype=D64, requires_grad=True)
        return (mod(levels, proj) if kind == "sff" else mod(q, levels, proj)), q

    out, q = run(0, torch.zeros(0, dtype=torch.long))
    assert out.shape == (0, 8)
    out.sum().backward()  # no error; nothing to propagate
    for l in levels:
        l.grad = None
    out, q = run(4, torch.zeros(4, dtype=torch.long))  # sample 1 has no voxels
    assert torch.isfinite(out).all()
    (out * torch.randn(out.shape, generator=gen, dtype=D64)).sum().backward()
    for l in levels:
        assert torch.count_nonzero(l.grad[1]) == 0
        assert torch.count_nonzero(l.grad[0]) > 0


@pytest.mark.parametrize("kind", ["sff", "msdff"])
def test_permutation_and_batch_independence(kind):
    gen = torch.Generator().manual_seed(6)
    levels, uv, valid, bidx = scene(gen, n=9, chans=(4, 4))
    if kind == "sff":
        mod = SFF([4, 4], 6, dtype=D64)
    else:
        mod = MSDFF(6, 4, value_dim=8, num_heads=2, num_levels=2, num_points=3, dtype=D64)
        randomize_msdff(mod, gen)
    mod.eval()
    query = torch.randn(9, 6, generator=gen, dtype=D64)

    def run(lv, q, u, va, b):
        proj = make_projection(u, va, b)
        return mod(lv, proj) if kind == "sff" else mod(q, lv, proj)

    out = run(levels, query, uv, valid, bidx)
    perm = torch.randperm(9, generator=gen)
    assert_close(run(levels, query[perm], uv[perm], valid[perm], bidx[perm]), out[perm])
    # Changing sample 1's images never changes a sample-0 voxel's output.
    other = [l.clone() for l in levels]
    for l in other:
        l[1] = torch.randn(l[1].shape, generator=gen, dtype=D64)
    out2 = run(other, query, uv, valid, bidx)
    s0 = bidx == 0
    assert s0.any() and (~s0).any()
    assert torch.equal(out2[s0], out[s0])
    assert not torch.allclose(out2[~s0 & valid.any(1)], out[~s0 & valid.any(1)])


# ---------------------------------------------------------------------------------------------------
# MSDFF
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize(
    "method,value_projection",
    [("auto", "after_sampling"), ("reference", "after_sampling"), ("fast", "after_sampling"),
     ("fast", "before_sampling"), ("reference", "before_sampling")],
)
def test_msdff_sample_then_project_equals_project_then_sample(method, value_projection, width, device):
    gen = torch.Generator().manual_seed(7)
    levels, uv, valid, bidx = scene(gen, chans=(4, 4), sizes=((5, 6), (3, 4)))
    uv[3] = torch.tensor([0.02, 0.97], dtype=D64)  # near the border: samples partly outside (mass < 1)
    valid[3] = True
    mod = MSDFF(8, 4, num_heads=2, num_levels=2, num_points=3, method=method,
                value_projection=value_projection, dtype=D64, **width_kw(width, 8)).eval()
    assert mod.value_proj.weight.shape == ((4, 4) if width == "paper" else (8, 4))
    randomize_msdff(mod, gen)
    query = torch.randn(7, 8, generator=gen, dtype=D64)
    want, off, _ = reference_msdff(mod, query, levels, uv, valid, bidx)
    # Make sure the bias-times-mass term matters: some sampling location reads outside the image.
    sizes = torch.tensor([[6.0, 5.0], [4.0, 3.0]], dtype=D64)
    loc = uv[3, 0] + off[3] / sizes[None, :, None, :]
    pix = loc * sizes[None, :, None, :] - 0.5
    assert ((pix < 0) | (pix > sizes[None, :, None, :] - 1)).any()
    out = mod.to(device)(query.to(device), [l.to(device) for l in levels], make_projection(uv, valid, bidx, device))
    assert_close(out.detach().cpu(), want)


@pytest.mark.parametrize("width", WIDTHS)
def test_msdff_default_init_matches_reference(width):
    gen = torch.Generator().manual_seed(8)
    levels, uv, valid, bidx = scene(gen, v=1, chans=(4, 4))
    mod = MSDFF(8, 4, num_heads=4, num_levels=2, num_points=2, dtype=D64, **width_kw(width, 8)).eval()
    randomize_norm(mod.norm, gen)
    query = torch.randn(7, 8, generator=gen, dtype=D64)
    want, _, att = reference_msdff(mod, query, levels, uv, valid, bidx)
    assert torch.allclose(att, torch.full_like(att, 0.25))  # zero-initialised attention: uniform
    assert_close(mod(query, levels, make_projection(uv, valid, bidx)), want)


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("value_projection", ["after_sampling", "before_sampling"])
def test_msdff_gradcheck(value_projection, width):
    # Eval-mode BN (a fixed affine map) with random running statistics; sampling offsets and attention
    # weights are randomised so the gradient w.r.t. the query goes through locations and softmax.
    gen = torch.Generator().manual_seed(9)
    levels, uv, valid, bidx = scene(gen, n=4, chans=(2, 2), sizes=((4, 5), (2, 3)))
    mod = MSDFF(4, 2, num_heads=2, num_levels=2, num_points=2, value_projection=value_projection, dtype=D64,
                **width_kw(width, 4)).eval()
    randomize_msdff(mod, gen, scale=0.3)
    query = torch.randn(4, 4, generator=gen, dtype=D64)

    def fn(q, l0, l1, uv_):
        return mod(q, [l0, l1], make_projection(uv_, valid, bidx))

    assert gradcheck64(fn, (query, levels[0], levels[1], uv))


@pytest.mark.parametrize("width", WIDTHS)
def test_msdff_invalid_voxels_pass_nothing(width):
    gen = torch.Generator().manual_seed(10)
    levels, uv, valid, bidx = scene(gen, chans=(6, 6))
    mod = MSDFF(4, 6, num_heads=2, num_levels=2, num_points=2, dtype=D64, **width_kw(width, 4)).eval()
    randomize_msdff(mod, gen)
    query = torch.randn(7, 4, generator=gen, dtype=D64)
    levels = [l.requires_grad_(True) for l in levels]
    out = mod(query, levels, make_projection(uv, valid, bidx))
    assert torch.equal(out[0], torch.zeros(4, dtype=D64))  # voxel 0 is seen by no camera
    keep = valid.any(1)
    g_full = torch.autograd.grad(out.sum(), levels)
    sub = mod(query[keep], levels, make_projection(uv[keep], valid[keep], bidx[keep]))
    g_sub = torch.autograd.grad(sub.sum(), levels)
    for a, b in zip(g_full, g_sub):
        assert_close(a, b)
    none = torch.zeros_like(valid)
    out = mod(query, levels, make_projection(uv, none, bidx))
    assert torch.equal(out, torch.zeros(7, 4, dtype=D64))
    grads = torch.autograd.grad(out.sum(), levels, allow_unused=True)
    assert all(g is None or torch.count_nonzero(g) == 0 for g in grads)


@pytest.mark.parametrize("width", WIDTHS)
def test_msdff_parameters_match_deformable_detr(width):
    e, m, l, p, c = 16, 8, 3, 2, 24
    mod = MSDFF(e, c, num_heads=m, num_levels=l, num_points=p, **width_kw(width, e))
    d = c if width == "paper" else e
    shapes = {k: tuple(v.shape) for k, v in mod.state_dict().items()}
    want = {
        "sampling_offsets.weight": (m * l * p * 2, e), "sampling_offsets.bias": (m * l * p * 2,),
        "attention_weights.weight": (m * l * p, e), "attention_weights.bias": (m * l * p,),
        "value_proj.weight": (d, c), "value_proj.bias": (d,),
        "output_proj.weight": (e, d), "output_proj.bias": (e,),
    }
    for k, s in want.items():
        assert shapes[k] == s, k
    # An MSDeformAttn state dict (same keys) loads; only our norm is extra.
    detr = {k: torch.randn(s) for k, s in want.items()}
    res = mod.load_state_dict(detr, strict=False)
    assert not res.unexpected_keys and all(k.startswith("norm.") for k in res.missing_keys)
    assert torch.equal(mod.value_proj.weight, detr["value_proj.weight"])

    mod.reset_parameters()
    assert torch.count_nonzero(mod.sampling_offsets.weight) == 0
    assert torch.count_nonzero(mod.attention_weights.weight) == 0
    assert torch.count_nonzero(mod.attention_weights.bias) == 0
    for lin in (mod.value_proj, mod.output_proj):
        assert torch.count_nonzero(lin.bias) == 0
        bound = math.sqrt(6.0 / sum(lin.weight.shape))
        assert lin.weight.abs().max() <= bound and lin.weight.std() > bound / 3
    # Direction grid, hand-worked for 8 heads: directions at multiples of 45 degrees scaled so that
    # max(|cos|, |sin|) = 1, point p at (p + 1) times that direction, the same for every level.
    dirs = torch.tensor([[1, 0], [1, 1], [0, 1], [-1, 1], [-1, 0], [-1, -1], [0, -1], [1, -1]], dtype=torch.float32)
    bias = mod.sampling_offsets.bias.view(m, l, p, 2)
    for level in range(l):
        for pt in range(p):
            torch.testing.assert_close(bias[:, level, pt], dirs * (pt + 1), atol=1e-6, rtol=0)


def test_msdff_offsets_are_in_level_pixels():
    # One head, one point per level, zero weights: the offset bias (1, 0) moves the sample exactly one
    # pixel right on every level, whatever the level's size.
    levels = [torch.arange(24, dtype=D64).view(1, 1, 1, 4, 6), torch.arange(6, dtype=D64).view(1, 1, 1, 2, 3)]
    mod = MSDFF(2, 1, value_dim=2, num_heads=1, num_levels=2, num_points=1, dtype=D64).eval()
    with torch.no_grad():
        mod.value_proj.weight.copy_(torch.tensor([[1.0], [0.0]]))
        mod.output_proj.weight.copy_(torch.eye(2))
    # reference at pixel (1, 1) of level 0 = (0.5, 0.5) of level 1 -> +1 pixel: (2, 1) and (1.5, 0.5).
    uv = torch.tensor([[[1.5 / 6, 1.5 / 4]]], dtype=D64)
    proj = make_projection(uv, torch.ones(1, 1, dtype=torch.bool), torch.zeros(1, dtype=torch.long))
    out = mod(torch.zeros(1, 2, dtype=D64), levels, proj)
    # level 0: pixel (x=2, y=1) of arange(24).view(4, 6) = 8; level 1: the reference is at pixel
    # (0.25, 0.25), moved to (1.25, 0.25) of arange(6).view(2, 3) = 3 y + x = 2 (all corners inside).
    want = torch.tensor(0.5 * 8.0 + 0.5 * 2.0, dtype=D64)
    bn = mod.norm
    assert_close(out[0, 0], (want - bn.running_mean[0]) / torch.sqrt(bn.running_var[0] + bn.eps))


# ---------------------------------------------------------------------------------------------------
# QueryInit
# ---------------------------------------------------------------------------------------------------
def test_query_init_hand_worked():
    qi = QueryInit(2, 1, 3, (0.0, -10.0, -2.0, 20.0, 10.0, 2.0), dtype=D64).eval()
    centers = torch.tensor([[0.0, -10.0, -2.0], [20.0, 10.0, 2.0], [5.0, 0.0, 1.0]], dtype=D64)
    p = torch.tensor([[0, 0, 0], [1, 1, 1], [0.25, 0.5, 0.75]], dtype=D64)
    assert_close(qi.normalized_centers(centers), p)
    f_vox = torch.randn(3, 2, dtype=D64)
    f_img = torch.randn(3, 1, dtype=D64)
    x = torch.cat([f_vox, f_img, p], 1)
    assert_close(qi(f_vox, f_img, centers), ref_bn_eval(x @ qi.linear.weight.T + qi.linear.bias, qi.norm))
    with pytest.raises(MSSFError, match="f_img0"):
        qi(f_vox, torch.zeros(3, 2, dtype=D64), centers)
    with pytest.raises(MSSFError, match="point_cloud_range"):
        QueryInit(2, 1, 3, (0, 0, 0, 1, 1))


# ---------------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------------
def test_bad_inputs_name_the_argument():
    l2i = torch.eye(3, 4).expand(2, 1, 3, 4)
    pts, pb = torch.zeros(1, 3), torch.zeros(1, dtype=torch.long)
    ok = [torch.zeros(2, 4, 6, 8), torch.zeros(2, 4, 3, 4)]
    FusionInputs(ok, l2i, (12, 16), pts, pb)
    with pytest.raises(MSSFError, match=r"image_features\[1\]"):
        FusionInputs([ok[0], torch.zeros(3, 4, 3, 4)], l2i, (12, 16), pts, pb)
    with pytest.raises(MSSFError, match=r"image_features\[0\]"):
        FusionInputs([torch.zeros(2, 3, 4, 6, 8)], l2i, (12, 16), pts, pb)  # V=3 vs lidar2img V=1
    with pytest.raises(MSSFError, match=r"image_features\[0\]"):
        FusionInputs([torch.zeros(4, 6, 8)], l2i, (12, 16), pts, pb)
    with pytest.raises(MSSFError, match="image_size"):
        FusionInputs(ok, l2i, (12,), pts, pb)

    sff = SFF([4, 4], 8)
    proj = make_projection(torch.rand(3, 1, 2), torch.ones(3, 1, dtype=torch.bool), torch.zeros(3, dtype=torch.long))
    with pytest.raises(MSSFError, match=r"image_features\[1\]"):
        sff([ok[0], torch.zeros(2, 5, 3, 4)], proj)
    with pytest.raises(MSSFError, match="image_features: expected 2 levels"):
        sff(ok[:1], proj)
    bad_uv = make_projection(torch.rand(3, 2), torch.ones(3, 1, dtype=torch.bool), torch.zeros(3, dtype=torch.long))
    with pytest.raises(MSSFError, match=r"projection\.uv"):
        sff(ok, bad_uv)
    with pytest.raises(MSSFError, match="in_channels"):
        SFF(4, 8)

    mod = MSDFF(8, 4, num_heads=2, num_levels=2, num_points=1)
    with pytest.raises(MSSFError, match="query"):
        mod(torch.zeros(3, 7), ok, proj)
    with pytest.raises(MSSFError, match=r"image_features\[0\]"):
        mod(torch.zeros(3, 8), [torch.zeros(2, 5, 6, 8), torch.zeros(2, 5, 3, 4)], proj)
    with pytest.raises(MSSFError, match="value_channels"):
        MSDFF(8, [4, 8], num_heads=2, num_levels=2)
    with pytest.raises(MSSFError, match="value_dim.*defaults to value_channels"):
        MSDFF(8, 6, num_heads=4)  # value_dim = value_channels = 6 heads cannot split into 4
    with pytest.raises(MSSFError, match="value_dim: expected a multiple of num_heads=4.*got 10"):
        MSDFF(8, 4, value_dim=10, num_heads=4)
    with pytest.raises(MSSFError, match="value_dim"):
        MSDFF(8, 4, value_dim=0, num_heads=4)
    MSDFF(10, 4, num_heads=4)  # embed_dim need not be a multiple of num_heads (the heads split value_dim)
    with pytest.raises(MSSFError, match="method"):
        MSDFF(8, 8, method="cuda")
    with pytest.raises(MSSFError, match="value_projection"):
        MSDFF(8, 8, value_projection="never")


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("layout", ["nchw", "channels_last"])
def test_msdff_touched_pixels_equals_reference_with_all_gradients(dtype, layout, width):
    # value_projection="before_sampling" with method "auto" projects only the touched pixels (or whole
    # levels); it must equal projecting every pixel + grid_sample (method "reference") in the output
    # and in the gradient of every parameter, the query, the image and uv.
    gen = torch.Generator().manual_seed(21)
    levels, uv, valid, bidx = scene(gen, n=9, chans=(4, 4), sizes=((6, 9), (3, 5)))
    uv[3] = torch.tensor([0.02, 0.97], dtype=D64)  # near the border: samples partly outside
    valid[3] = True
    mods = {}
    for method in ("reference", "auto"):
        mod = MSDFF(8, 4, num_heads=2, num_levels=2, num_points=3, method=method,
                    value_projection="before_sampling", dtype=D64, **width_kw(width, 8)).eval()
        randomize_msdff(mod, torch.Generator().manual_seed(22))
        mods[method] = mod.to(dtype)
    query = torch.randn(9, 8, generator=gen, dtype=D64).to(dtype)
    go = torch.randn(9, 8, generator=gen, dtype=D64).to(dtype)
    results = {}
    for method, mod in mods.items():
        lv = [l.to(dtype).requires_grad_(True) for l in levels]
        feeds = [l.reshape(-1, *l.shape[2:]).contiguous(memory_format=torch.channels_last).view(l.shape)
                 if layout == "channels_last" else l for l in lv]
        q = query.clone().requires_grad_(True)
        u = uv.to(dtype).requires_grad_(True)
        out = mod(q, feeds, make_projection(u, valid, bidx))
        params = list(mod.parameters())
        grads = torch.autograd.grad((out * go).sum(), [q, u, *lv, *params], allow_unused=True)
        results[method] = (out.detach(), grads)
    assert_close(results["auto"][0], results["reference"][0], msg="out")
    names = ["query", "uv", "level0", "level1"] + [n for n, _ in mods["auto"].named_parameters()]
    for name, a, b in zip(names, results["auto"][1], results["reference"][1]):
        assert (a is None) == (b is None), name
        if b is not None:
            assert_close(a, b, msg=f"grad {name}")
    by_name = dict(zip(names, results["reference"][1]))
    assert by_name["value_proj.weight"].abs().sum() > 0 and by_name["value_proj.bias"].abs().sum() > 0


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("method", ["auto", "fast", "reference"])
def test_msdff_one_camera_all_seen_matches_reference(method, width):
    # MSDFF's shortcut for one camera that sees every voxel (no gather/scatter) against the reference
    gen = torch.Generator().manual_seed(23)
    levels, uv, valid, bidx = scene(gen, v=1, n=8, chans=(4, 4))
    valid[:] = True
    uv[2] = torch.tensor([0.01, 0.99], dtype=D64)  # partly outside
    mod = MSDFF(8, 4, num_heads=2, num_levels=2, num_points=3, method=method, dtype=D64,
                **width_kw(width, 8)).eval()
    randomize_msdff(mod, gen)
    query = torch.randn(8, 8, generator=gen, dtype=D64)
    want, _, _ = reference_msdff(mod, query, levels, uv, valid, bidx)
    assert_close(mod(query, levels, make_projection(uv, valid, bidx)), want)
    assert gradcheck64(lambda q, l0, u: mod(q, [l0, levels[1]], make_projection(u, valid, bidx)),
                       (query, levels[0], uv))
