"""Tests of ``mssf_blocks.functional.ms_deform_sample_project`` ("chunked" and every plan of
"touched") against naive loops and the ``ms_deform_sample`` reference followed by the projection by hand,
gradients included. The sampling itself: ``test_sampling.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional import ms_deform_sample_project
from mssf_blocks.functional.sampling import ms_deform_sample
from mssf_blocks.testing import assert_close, gradcheck64

sys.path.insert(0, str(Path(__file__).parent))
from sampling_references import F64, border_locations, naive_ms_deform, random_inputs  # noqa: E402


# ---------------------------------------------------------------------------------------------------
# ms_deform_sample_project(method="chunked"): sample, then project
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mv", [1, 2])
@pytest.mark.parametrize("chunk_size", [None, 1, 4, 100])
def test_sample_project_equals_reference_then_projection(mv, chunk_size):
    # independent: naive loop sampling, then the per-head projection and bias * mass by hand
    values, image_index, locations, weights = random_inputs(num_images=2, mv=mv, m=2, d=3, q=7, seed=8)
    g = torch.Generator().manual_seed(9)
    proj_w = torch.randn(2, 4, 3, generator=g, dtype=F64)
    proj_b = torch.randn(2, 4, generator=g, dtype=F64)
    sampled, mass = naive_ms_deform(values, image_index, locations, weights)
    expected = torch.einsum("qmc,mdc->qmd", sampled, proj_w) + mass[..., None] * proj_b
    out = ms_deform_sample_project(values, image_index, locations, weights, proj_w, proj_b, chunk_size=chunk_size)
    assert out.shape == (7, 2, 4)
    assert_close(out, expected)
    # gradients of every input equal those of the unchunked reference composition
    inputs = [v.clone().requires_grad_(True) for v in values] + [
        t.clone().requires_grad_(True) for t in (locations, weights, proj_w, proj_b)
    ]
    go = torch.randn(7, 2, 4, generator=g, dtype=F64)

    def grads(fn):
        return torch.autograd.grad(fn(*inputs), inputs, go)

    def ref(v0, v1, loc, wt, pw, pb):
        s, ms = ms_deform_sample([v0, v1], image_index, loc, wt, method="reference", return_mass=True)
        return torch.einsum("qmc,mdc->qmd", s, pw) + ms[..., None] * pb

    def ours(v0, v1, loc, wt, pw, pb):
        return ms_deform_sample_project([v0, v1], image_index, loc, wt, pw, pb, chunk_size=chunk_size)

    for a, b in zip(grads(ours), grads(ref)):
        assert_close(a, b)


def test_sample_project_gradcheck_and_errors():
    values, image_index, locations, weights = random_inputs(
        num_images=2, mv=1, m=2, d=2, sizes=((3, 4), (2, 2)), q=3, p=2, seed=10
    )
    proj_w = torch.randn(2, 3, 2, dtype=F64)
    proj_b = torch.randn(2, 3, dtype=F64)
    assert gradcheck64(
        lambda v0, v1, loc, wt, pw, pb: ms_deform_sample_project([v0, v1], image_index, loc, wt, pw, pb, chunk_size=2),
        (values[0], values[1], locations, weights, proj_w, proj_b),
    )
    with pytest.raises(MSSFError, match="proj_weight"):
        ms_deform_sample_project(values, image_index, locations, weights, proj_w[:, :, :1])
    with pytest.raises(MSSFError, match="proj_bias"):
        ms_deform_sample_project(values, image_index, locations, weights, proj_w, proj_b[:, :2])
    with pytest.raises(MSSFError, match="chunk_size"):
        ms_deform_sample_project(values, image_index, locations, weights, proj_w, chunk_size=0)


# ---------------------------------------------------------------------------------------------------
# ms_deform_sample_project(method="touched"): project the touched pixels, then sample
# ---------------------------------------------------------------------------------------------------
def project_reference(values, image_index, locations, weights, proj_w, proj_b):
    """grid_sample reference of the raw channels, then the per-head projection and bias * mass."""
    s, ms = ms_deform_sample(values, image_index, locations, weights, method="reference", return_mass=True)
    return torch.einsum("qmc,mdc->qmd", s, proj_w) + ms[..., None] * proj_b


def touched(values, image_index, locations, weights, proj_w, proj_b, branch):
    """The "touched" method with its per-level plan forced (or the cost model's, branch "auto")."""
    from mssf_blocks.functional.deform import touched as sampling

    if branch == "auto":
        return ms_deform_sample_project(values, image_index, locations, weights, proj_w, proj_b, method="touched")
    return sampling.sample_project(values, image_index, locations, weights, proj_w, proj_b, branch)


def channels_last(values):
    return [v[:, 0].contiguous(memory_format=torch.channels_last)[:, None] for v in values]


# MSDFF's value widths: heads together as wide as the raw channels (the paper's value_dim =
# value_channels), narrower (value_dim = embed_dim < C), or wider than them.
HEAD_WIDTHS = [pytest.param(4, 2, id="paper_width"), pytest.param(4, 1, id="narrow_width"),
               pytest.param(3, 4, id="wide_heads")]


@pytest.mark.parametrize("d_raw,d_out", HEAD_WIDTHS)
@pytest.mark.parametrize("branch", ["project", "sample", "dense", "direct", "auto"])
def test_touched_equals_naive_loop(branch, d_raw, d_out):
    # independent: naive loop sampling, then the per-head projection and bias * mass by hand
    values, image_index, locations, weights = random_inputs(num_images=2, mv=1, m=2, d=d_raw, q=7, seed=8,
                                                            spread=0.5)
    g = torch.Generator().manual_seed(9)
    proj_w = torch.randn(2, d_out, d_raw, generator=g, dtype=F64)
    proj_b = torch.randn(2, d_out, generator=g, dtype=F64)
    sampled, mass = naive_ms_deform(values, image_index, locations, weights)
    expected = torch.einsum("qmc,mdc->qmd", sampled, proj_w) + mass[..., None] * proj_b
    assert bool((mass < weights.sum((2, 3)) - 1e-6).any())  # some corners read the zero padding
    for vals in (values, channels_last(values)) if branch != "direct" else (channels_last(values),):
        out = touched(vals, image_index, locations, weights, proj_w, proj_b, branch)
        assert out.shape == (7, 2, d_out)
        assert_close(out, expected)
        assert_close(touched(vals, image_index, locations, weights, proj_w, None, branch),
                     torch.einsum("qmc,mdc->qmd", sampled, proj_w))


@pytest.mark.parametrize("d_raw", [pytest.param(4, id="wide_heads"), pytest.param(6, id="paper_width"),
                                   pytest.param(9, id="narrow_width")])  # 3 heads of 2 channels
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("where", ["random", "borders"])
@pytest.mark.parametrize("branch,layout", [(b, l) for b in ("project", "sample", "dense") for l in ("nchw", "channels_last")]
                         + [("direct", "channels_last")])
def test_touched_equals_reference_forward_and_all_gradients(dtype, where, branch, layout, d_raw):
    sizes = ((8, 16), (4, 8), (2, 4))
    values, image_index, locations, weights = random_inputs(
        num_images=3, mv=1, m=3, d=d_raw, sizes=sizes, q=17, p=2, dtype=dtype, spread=0.4
    )
    if where == "borders":  # pixel centres, pixel borders, image edges and outside
        locations = border_locations(sizes, 17, 3, 2, dtype)
    g = torch.Generator().manual_seed(11)
    proj_w = torch.randn(3, 2, d_raw, generator=g, dtype=dtype)
    proj_b = torch.randn(3, 2, generator=g, dtype=dtype)
    go = torch.randn(17, 3, 2, generator=g, dtype=dtype)

    def run(fn):
        vals = [v.detach().clone().requires_grad_(True) for v in values]
        if layout == "channels_last":
            vals = [v.detach()[:, 0].contiguous(memory_format=torch.channels_last).requires_grad_(True)
                    for v in values]
            inputs5 = [v[:, None] for v in vals]
        else:
            inputs5 = vals
        rest = [t.detach().clone().requires_grad_(True) for t in (locations, weights, proj_w, proj_b)]
        out = fn(inputs5, image_index, *rest)
        return out.detach(), torch.autograd.grad((out * go).sum(), vals + rest)

    out_r, grads_r = run(project_reference)
    out_t, grads_t = run(lambda *a: touched(*a, branch))
    assert_close(out_t, out_r, msg="out")
    names = [f"values[{i}]" for i in range(len(sizes))] + ["locations", "weights", "proj_weight", "proj_bias"]
    for name, a, b in zip(names, grads_t, grads_r):
        assert_close(a.reshape(b.shape), b, msg=f"grad {name}")
    assert all(bool(gr.abs().sum() > 0) for gr in grads_r)  # not vacuous


@pytest.mark.parametrize("branch", ["project", "sample", "dense", "direct"])
def test_touched_gradcheck(branch):
    values, image_index, locations, weights = random_inputs(
        num_images=2, mv=1, m=2, d=2, sizes=((3, 4), (2, 2)), q=3, p=2, seed=10, spread=0.3
    )
    if branch == "direct":
        values = channels_last(values)
    proj_w = torch.randn(2, 3, 2, dtype=F64)
    proj_b = torch.randn(2, 3, dtype=F64)
    assert gradcheck64(
        lambda v0, v1, loc, wt, pw, pb: touched([v0, v1], image_index, loc, wt, pw, pb, branch),
        (values[0], values[1], locations, weights, proj_w, proj_b),
    )


@pytest.mark.parametrize("layout", ["nchw", "channels_last"])
def test_touched_project_with_gradients_keeps_no_copy_of_the_raw_rows(layout):
    # With gradients the "project" plan must not keep the gathered (U, D) raw rows for its weight
    # gradient (it gathers them again): on a 256-channel P2 that copy was 53 MiB. Record what autograd
    # saves while the forward runs; the raw rows would be the only saved tensor with D columns other
    # than the (E, D) weight and the level itself (kept as a view, every pixel).
    d_raw = 64
    values, image_index, locations, weights = random_inputs(
        num_images=2, mv=1, m=2, d=d_raw, sizes=((12, 20),), q=4, p=2, seed=12, spread=0.0
    )
    if layout == "channels_last":
        values = channels_last(values)
    n_pix = 2 * 12 * 20
    g = torch.Generator().manual_seed(13)
    proj_w = torch.randn(2, 3, d_raw, generator=g, dtype=F64, requires_grad=True)
    proj_b = torch.randn(2, 3, generator=g, dtype=F64, requires_grad=True)
    loc = locations.clone().requires_grad_(True)
    shapes = []

    def pack(t):
        shapes.append(tuple(t.shape))
        return t

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
        out = touched(values, image_index, loc, weights, proj_w, proj_b, "project")
    rows = [sh for sh in shapes if len(sh) == 2 and sh[1] == d_raw and sh[0] not in (2 * 3, n_pix)]
    assert shapes and not rows, rows
    # and it is still the right answer, gradients included
    want = project_reference(values, image_index, loc, weights, proj_w, proj_b)
    assert_close(out, want)
    go = torch.randn(out.shape, generator=g, dtype=F64)
    for a, b in zip(torch.autograd.grad((out * go).sum(), [loc, proj_w, proj_b]),
                    torch.autograd.grad((want * go).sum(), [loc, proj_w, proj_b])):
        assert_close(a, b)


def test_touched_all_outside_empty_and_batch_independence():
    values, image_index, locations, weights = random_inputs(num_images=3, mv=1, m=2, d=3, q=20, seed=12)
    g = torch.Generator().manual_seed(13)
    proj_w = torch.randn(2, 2, 3, generator=g, dtype=F64)
    proj_b = torch.randn(2, 2, generator=g, dtype=F64)
    # every point far outside the image: zero padding everywhere, bias included; gradients are zero
    for branch in ("auto", "project", "sample", "dense", "direct"):
        far = (locations + 5.0).requires_grad_(True)
        pw = proj_w.clone().requires_grad_(True)
        out = touched(channels_last(values) if branch == "direct" else values, image_index, far, weights, pw,
                      proj_b, branch)
        assert torch.equal(out, torch.zeros_like(out)), branch
        out.sum().backward()
        assert torch.equal(far.grad, torch.zeros_like(far)), branch
        assert pw.grad is None or torch.equal(pw.grad, torch.zeros_like(pw)), branch  # no pixel read
    # no queries: an empty result that can be backpropagated
    loc0 = torch.zeros(0, 2, 2, 3, 2, dtype=F64, requires_grad=True)
    out0 = ms_deform_sample_project(values, torch.zeros(0, dtype=torch.long), loc0, weights[:0], proj_w, proj_b,
                                    method="touched")
    assert out0.shape == (0, 2, 2)
    out0.sum().backward()
    assert torch.equal(loc0.grad, torch.zeros_like(loc0))
    # sample i never sees image j
    base = ms_deform_sample_project(values, image_index, locations, weights, proj_w, proj_b, method="touched")
    for j in range(3):
        changed = [v.clone() for v in values]
        for v in changed:
            v[j] = torch.randn_like(v[j]) * 100
        out = ms_deform_sample_project(changed, image_index, locations, weights, proj_w, proj_b, method="touched")
        assert torch.equal(out[image_index != j], base[image_index != j])
        assert not torch.equal(out[image_index == j], base[image_index == j])


@pytest.mark.parametrize("branch", ["project", "sample", "dense", "direct"])
def test_touched_leaves_out_only_the_queries_that_read_nothing(branch, monkeypatch):
    # MSDFF's static layout puts invalid (voxel, camera) pairs at uv = -1: such queries read no pixel and
    # are left out. Queries with one point just inside the last reading position must stay: pixel
    # coordinate x = -0.999 (a corner at x = 0, weight 0.001), x = W - 0.001, and exactly x = -1 (corner
    # weight 0 but a non-zero location gradient), each with every other point far outside.
    from mssf_blocks.functional.deform import touched as touched_mod

    sizes = ((6, 8), (3, 4))
    values, image_index, locations, weights = random_inputs(num_images=2, mv=1, m=2, d=3, sizes=sizes, q=12, p=2,
                                                            seed=21, spread=0.1)
    if branch == "direct":
        values = channels_last(values)
    locations = locations.clone()
    locations[6:] = -1.0 + 0.2 * locations[6:]  # the far-outside queries: every point outside every level
    edge = {8: (1, -0.999), 9: (0, 8 - 0.001), 10: (1, -1.0)}  # query: (level, pixel x of one point)
    for qi, (lvl, x) in edge.items():
        w = sizes[lvl][1]
        locations[qi, 1, lvl, 0] = torch.tensor([(x + 0.5) / w, 0.5], dtype=F64)
    g = torch.Generator().manual_seed(22)
    proj_w, proj_b = torch.randn(2, 4, 3, generator=g, dtype=F64), torch.randn(2, 4, generator=g, dtype=F64)
    go = torch.randn(12, 2, 4, generator=g, dtype=F64)
    seen = []
    real = touched_mod._level_points
    monkeypatch.setattr(touched_mod, "_level_points",
                        lambda loc, wt, sz, order: seen.append(order.numel()) or real(loc, wt, sz, order))

    def run(fn):
        inputs = [t.clone().requires_grad_(True) for t in (locations, weights, proj_w, proj_b)]
        out = fn(values, image_index, *inputs)
        return out, torch.autograd.grad((out * go).sum(), inputs)

    out_t, grads_t = run(lambda *a: touched_mod.sample_project(*a, branch, skip_unread=True))
    assert seen == [9]  # the 6 inside + the 3 edge queries; the other 3 never reach the plans
    out_r, grads_r = run(project_reference)
    assert_close(out_t, out_r)
    for name, a, b in zip(("locations", "weights", "proj_weight", "proj_bias"), grads_t, grads_r):
        assert_close(a, b, msg=f"grad {name}")
    assert torch.equal(out_t[[6, 7, 11]], torch.zeros(3, 2, 4, dtype=F64))
    for qi in edge:  # not vacuous: each edge query reads (x = -1: through its location gradient only)
        assert bool(grads_r[0][qi, 1].abs().sum() > 0), qi
    assert bool(out_r[8].abs().sum() > 0) and bool(out_r[9].abs().sum() > 0)


def test_project_methods_auto_and_errors():
    values, image_index, locations, weights = random_inputs(num_images=2, mv=2, m=2, d=2, q=5, seed=14)
    proj_w = torch.randn(2, 3, 2, dtype=F64)
    with pytest.raises(MSSFError, match="Mv = 1"):
        ms_deform_sample_project(values, image_index, locations, weights, proj_w, method="touched")
    with pytest.raises(MSSFError, match="method"):
        ms_deform_sample_project(values, image_index, locations, weights, proj_w, method="gemm")
    # auto: "chunked" for per-head maps (Mv = M), "touched" for shared maps; both equal the reference
    assert_close(ms_deform_sample_project(values, image_index, locations, weights, proj_w, method="auto"),
                 ms_deform_sample_project(values, image_index, locations, weights, proj_w, method="chunked"))
    shared = [v[:, :1] for v in values]
    assert_close(ms_deform_sample_project(shared, image_index, locations, weights, proj_w, method="auto"),
                 project_reference(shared, image_index, locations, weights, proj_w, torch.zeros(2, 3, dtype=F64)))
