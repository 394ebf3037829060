"""The raw-row plans of ``ms_deform_sample_project(method="touched")`` bag their queries in blocks.

The blocks (``plan_costs._RAW_CHUNK_BYTES`` of samples at a time, recomputed in backward when
gradients are needed) must give the reference's values and gradients whatever the block size, keep
the non-finite-pixel rule, and not keep the raw ``(M * Q, D)`` samples for backward.
"""

from __future__ import annotations

import pytest
import torch

from mssf_blocks.functional.deform import touched as touched_mod
from mssf_blocks.functional.deform.touched import blocks
from mssf_blocks.functional.sampling import ms_deform_sample
from mssf_blocks.testing import assert_close

F64 = torch.float64


def inputs(q=23, m=3, d_raw=6, d_out=2, p=2, sizes=((8, 16), (4, 8), (2, 4)), num_images=2, dtype=F64, seed=0,
           lo=-0.15, hi=1.15):
    g = torch.Generator().manual_seed(seed)
    values = [torch.randn(num_images, 1, d_raw, h, w, generator=g, dtype=dtype) for h, w in sizes]
    image_index = torch.randint(0, num_images, (q,), generator=g)
    # some corners outside the maps (zero padding), most inside
    locations = lo + (hi - lo) * torch.rand(q, m, len(sizes), p, 2, generator=g, dtype=dtype)
    weights = torch.rand(q, m, len(sizes), p, generator=g, dtype=dtype)
    proj_w = torch.randn(m, d_out, d_raw, generator=g, dtype=dtype)
    proj_b = torch.randn(m, d_out, generator=g, dtype=dtype)
    return values, image_index, locations, weights, proj_w, proj_b


def reference(values, image_index, locations, weights, proj_w, proj_b):
    """grid_sample of the raw channels (an independent code path), then the per-head projection."""
    s, mass = ms_deform_sample(values, image_index, locations, weights, method="reference", return_mass=True)
    return torch.einsum("qmc,mdc->qmd", s, proj_w) + mass[..., None] * proj_b


def channels_last(v):
    return v[:, 0].contiguous(memory_format=torch.channels_last)[:, None]


def run(fn, values, image_index, locations, weights, proj_w, proj_b, go, layout):
    leaves = [t.detach().clone().requires_grad_(True) for t in (*values, locations, weights, proj_w, proj_b)]
    vals = leaves[: len(values)]
    vals5 = [channels_last(v) for v in vals] if layout == "channels_last" else vals
    out = fn(vals5, image_index, *leaves[len(values):])
    return out.detach(), torch.autograd.grad((out * go).sum(), leaves)


@pytest.mark.parametrize("block_queries", [1, 4, 23, 1000])
@pytest.mark.parametrize("plan,layout", [("sample", "nchw"), ("sample", "channels_last"),
                                         ("direct", "channels_last"), (None, "channels_last")])
def test_blocks_equal_reference_forward_and_all_gradients(monkeypatch, plan, layout, block_queries):
    values, image_index, locations, weights, proj_w, proj_b = inputs()
    m, d_raw = proj_w.shape[0], proj_w.shape[2]
    # blocks of block_queries queries: M * block * D float64 samples
    monkeypatch.setattr(blocks, "_RAW_CHUNK_BYTES", m * d_raw * 8 * block_queries)
    go = torch.randn(23, m, proj_w.shape[1], dtype=F64, generator=torch.Generator().manual_seed(5))

    def ours(vals, ii, loc, wt, pw, pb):
        return touched_mod.sample_project(vals, ii, loc, wt, pw, pb, plan)

    out_r, g_r = run(reference, values, image_index, locations, weights, proj_w, proj_b, go, layout)
    out_t, g_t = run(ours, values, image_index, locations, weights, proj_w, proj_b, go, layout)
    assert_close(out_t, out_r, msg="out")
    names = ["values[0]", "values[1]", "values[2]", "locations", "weights", "proj_weight", "proj_bias"]
    for name, a, b in zip(names, g_t, g_r):
        assert_close(a, b, msg=f"grad {name}")
        assert bool(b.abs().sum() > 0), name  # not vacuous
    with torch.no_grad():  # the forward without gradients takes the plain (not checkpointed) blocks
        vals5 = [channels_last(v) for v in values] if layout == "channels_last" else values
        assert_close(ours(vals5, image_index, locations, weights, proj_w, proj_b), out_r, msg="no_grad out")


@pytest.mark.parametrize("block_queries", [3, 1000])
def test_blocks_keep_a_nan_in_an_unread_last_pixel_out(monkeypatch, block_queries):
    # The direct plan's out-of-map corners read the level's last row with weight 0; a NaN there must
    # reach neither the output nor any gradient (those corners are left out of their bags).
    values, image_index, locations, weights, proj_w, proj_b = inputs(lo=-0.2, hi=0.8, num_images=1)
    image_index = torch.zeros_like(image_index)
    m, d_raw = proj_w.shape[0], proj_w.shape[2]
    monkeypatch.setattr(blocks, "_RAW_CHUNK_BYTES", m * d_raw * 8 * block_queries)
    clean = [v.clone() for v in values]
    poisoned = [v.clone() for v in values]
    poisoned[0][..., -1, -1] = float("nan")  # bottom-right pixel of the 8 x 16 level: no corner at <= 0.8 reads it
    go = torch.ones(23, m, proj_w.shape[1], dtype=F64)

    def ours(vals, ii, loc, wt, pw, pb):
        return touched_mod.sample_project(vals, ii, loc, wt, pw, pb, "direct")

    out_r, g_r = run(reference, clean, image_index, locations, weights, proj_w, proj_b, go, "channels_last")
    out_t, g_t = run(ours, poisoned, image_index, locations, weights, proj_w, proj_b, go, "channels_last")
    assert bool(torch.isfinite(out_t).all())
    assert_close(out_t, out_r)
    for a, b in zip(g_t[3:], g_r[3:]):  # locations, weights, proj_weight, proj_bias
        assert bool(torch.isfinite(a).all())
        assert_close(a, b)


def test_backward_keeps_no_raw_samples(monkeypatch):
    # With gradients the blocks are recomputed in backward: nothing autograd keeps is as large as one
    # block of raw samples (M * block, D), let alone all of them.
    torch.manual_seed(0)
    q, m, d_raw, p = 400, 4, 64, 2
    values, image_index, locations, weights, proj_w, proj_b = inputs(q=q, m=m, d_raw=d_raw, d_out=8, p=p,
                                                                     sizes=((16, 24), (8, 12)), dtype=torch.float32,
                                                                     lo=0.0, hi=1.0)
    block = 100
    monkeypatch.setattr(blocks, "_RAW_CHUNK_BYTES", m * d_raw * 4 * block)
    values = [channels_last(v) for v in values]
    locations.requires_grad_(True)
    proj_w.requires_grad_(True)
    inputs_ptrs = {t.untyped_storage().data_ptr() for t in (*values, locations, weights, proj_w, proj_b)}
    saved = []

    def pack(t):
        if t.untyped_storage().data_ptr() not in inputs_ptrs:
            saved.append(t.numel())
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = touched_mod.sample_project(values, image_index, locations, weights, proj_w, proj_b, "direct")
    assert saved, "nothing saved: the test would be vacuous"
    assert max(saved) < m * block * d_raw, f"a saved tensor of {max(saved)} elements (raw samples kept?)"
    out.sum().backward()
    assert bool(proj_w.grad.abs().sum() > 0) and bool(locations.grad.abs().sum() > 0)


@pytest.mark.parametrize("block_queries", [1, 4, 23, 1000])
@pytest.mark.parametrize("plans", [("dense", "dense", "dense"), ("project", "project", "project"),
                                   ("direct", "dense", "project"), ("project", "direct", "dense")])
def test_forward_blocks_of_projected_and_raw_levels_equal_reference(monkeypatch, plans, block_queries):
    # Without gradients the projected levels ("dense", "project") are sampled block by block with the
    # raw-row levels: any mix of plans and any block size gives the reference's output.
    values, image_index, locations, weights, proj_w, proj_b = inputs()
    m, d_raw = proj_w.shape[0], proj_w.shape[2]
    monkeypatch.setattr(blocks, "_RAW_CHUNK_BYTES", m * d_raw * 8 * block_queries)
    level_plan = {tuple(v.shape[-2:]): plan for v, plan in zip(values, plans)}
    calls = []
    original = touched_mod._touched_level

    def per_level_plan(value, *args, **kwargs):  # (plan is the 7th positional argument)
        args = list(args)
        args[5] = level_plan[tuple(value.shape[-2:])]
        part = original(value, *args, **kwargs)
        calls.append(type(part).__name__)
        return part

    monkeypatch.setattr(touched_mod, "_touched_level", per_level_plan)
    want = reference(values, image_index, locations, weights, proj_w, proj_b)
    vals = [channels_last(v) for v in values]
    with torch.no_grad():
        got = touched_mod.sample_project(vals, image_index, locations, weights, proj_w, proj_b)
    assert_close(got, want)
    expected = ["_RawLevel" if plan == "direct" else "_ProjectedLevel" for plan in plans]
    assert calls == expected  # every level deferred to the blocks
