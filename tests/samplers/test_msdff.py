"""Tests for ``mssf_blocks.samplers.MSDFF`` against references written independently of the code under test
(``fusion_references.py``: every pixel projected with ``value_proj``, then per-level ``F.grid_sample``, naive
loops over voxels / cameras / heads), gradcheck in float64, Deformable DETR's parameter layout and
initialisation, hand-worked offsets. Shared SFF / MSDFF behaviour and bad input: ``test_sff.py``.
"""

import copy
import math
import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.samplers import MSDFF
from mssf_blocks.testing import assert_close, gradcheck64

sys.path.insert(0, str(Path(__file__).parent))
from fusion_references import (  # noqa: E402
    D64, WIDTHS, make_projection, randomize_msdff, reference_msdff, scene, width_kw)


# Tiny tensors: with 2 OpenMP threads on a loaded 2-core machine, each train-mode batch_norm call
# spins for ~10-50 ms (measured), which makes gradcheck 100x slower. One thread is plenty here.
pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------------------------------------
# MSDFF
# ---------------------------------------------------------------------------------------------------
# MSDFF against reference_msdff for every method and value projection on every device, its default
# initialisation, float64 gradcheck, state-dict round trip and compile smoke: the shared block checks,
# test_msdff_tester.py.


@pytest.mark.parametrize("width", WIDTHS)
def test_msdff_invalid_voxels_pass_nothing(width):
    gen = torch.Generator().manual_seed(10)
    levels, uv, valid, bidx = scene(gen, chans=(6, 6))
    mod = MSDFF(6, 4, num_heads=2, num_levels=2, num_points=2, dtype=D64, **width_kw(width, 4)).eval()
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
    mod = MSDFF(c, e, num_heads=m, num_levels=l, num_points=p, **width_kw(width, e))
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
    mod = MSDFF(1, 2, value_dim=2, num_heads=1, num_levels=2, num_points=1, dtype=D64).eval()
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
        mod = MSDFF(4, 8, num_heads=2, num_levels=2, num_points=3, method=method,
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
@pytest.mark.parametrize("unseen", [(), (0, 4, 8)], ids=["all_seen", "some_unseen"])
def test_msdff_one_camera_matches_reference(method, width, unseen):
    # MSDFF's paths for one camera (no gather/scatter when it sees every voxel; else the seen voxels'
    # queries only, output projection on their rows) against the reference, in eval and in train mode
    # (BatchNorm statistics of the seen voxels only), with gradients
    gen = torch.Generator().manual_seed(24)
    levels, uv, valid, bidx = scene(gen, v=1, n=9, chans=(4, 4))
    valid[:] = True
    valid[list(unseen)] = False
    if unseen:
        uv[4] = torch.tensor([5.0, -3.0], dtype=D64)  # an unseen voxel's uv is never read
    uv[2] = torch.tensor([0.01, 0.99], dtype=D64)  # partly outside
    mod = MSDFF(4, 8, num_heads=2, num_levels=2, num_points=3, method=method, dtype=D64,
                **width_kw(width, 8)).eval()
    randomize_msdff(mod, gen)
    query = torch.randn(9, 8, generator=gen, dtype=D64)
    want, _, _ = reference_msdff(mod, query, levels, uv, valid, bidx)
    got = mod(query, levels, make_projection(uv, valid, bidx))
    assert_close(got, want)
    assert torch.equal(got[list(unseen)], torch.zeros(len(unseen), 8, dtype=D64))
    seen = valid[:, 0]
    plain = copy.deepcopy(mod)  # its norm an exact identity in eval: the reference's pre-norm rows
    with torch.no_grad():
        plain.norm.running_mean.zero_()
        plain.norm.running_var.fill_(1.0 - plain.norm.eps)
        plain.norm.weight.fill_(1.0)
        plain.norm.bias.zero_()
    pre = reference_msdff(plain, query, levels, uv, valid, bidx)[0][seen]
    mod.train()
    out = mod(query, levels, make_projection(uv, valid, bidx))
    bn = (pre - pre.mean(0)) / torch.sqrt(pre.var(0, unbiased=False) + mod.norm.eps)
    assert_close(out[seen], bn * mod.norm.weight + mod.norm.bias)
    assert torch.equal(out[~seen], torch.zeros(len(unseen), 8, dtype=D64))
    mod.eval()
    assert gradcheck64(lambda q, l0, u: mod(q, [l0, levels[1]], make_projection(u, valid, bidx)),
                       (query, levels[0], uv))


def test_compiled_plan_with_gradients_comes_from_the_device_table(monkeypatch):
    # Under torch.compile (faked here: only the plan is asked) MSDFF's sampling is the op, except with
    # gradients on a device whose plan_costs.COMPILED_TRAINING entry is "grid" (the measured CPU choice).
    from mssf_blocks.samplers import msdff as msdff_mod
    from mssf_blocks.functional import plan_costs

    monkeypatch.setattr(msdff_mod, "_compiling_only", lambda: True)
    monkeypatch.setattr(msdff_mod, "use_static_path", lambda: True)
    m = MSDFF(8, 8, num_heads=2, num_levels=1, num_points=1)
    with torch.no_grad():
        assert m._plan("cpu") == ("sample_op", True)
    monkeypatch.setitem(plan_costs.COMPILED_TRAINING, "cpu", "grid")
    assert m._plan("cpu") == ("grid", True)
    monkeypatch.setitem(plan_costs.COMPILED_TRAINING, "cpu", "op")
    assert m._plan("cpu") == ("sample_op", True)
