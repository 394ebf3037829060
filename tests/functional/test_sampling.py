"""Tests of mssf_blocks.functional.sampling against naive loops, grid_sample and hand-worked numbers."""

from __future__ import annotations

import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.deform_project import ms_deform_sample_project
from mssf_blocks.functional.sampling import bilinear_sample, camera_mean, ms_deform_sample
from mssf_blocks.testing import assert_close, gradcheck64

F64 = torch.float64


# ---------------------------------------------------------------------------------------------------
# independent references
# ---------------------------------------------------------------------------------------------------
def naive_bilinear(img: torch.Tensor, u: float, v: float) -> torch.Tensor:
    """Bilinear interpolation by hand: ``img (C, H, W)``, align_corners=False, zero padding."""
    c, h, w = img.shape
    x, y = u * w - 0.5, v * h - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    out = torch.zeros(c, dtype=img.dtype)
    for yy in (y0, y0 + 1):
        for xx in (x0, x0 + 1):
            if 0 <= xx < w and 0 <= yy < h:
                wt = (1 - abs(x - xx)) * (1 - abs(y - yy))
                out += wt * img[:, yy, xx]
    return out


def naive_ms_deform(values, image_index, locations, weights):
    q, m, num_levels, p, _ = locations.shape
    d = values[0].shape[2]
    out = torch.zeros(q, m, d, dtype=locations.dtype)
    mass = torch.zeros(q, m, dtype=locations.dtype)
    for qi in range(q):
        for mi in range(m):
            for li in range(num_levels):
                val = values[li][int(image_index[qi])]
                img = val[mi if val.shape[0] > 1 else 0]
                ones = torch.ones(1, *img.shape[1:], dtype=img.dtype)
                for pi in range(p):
                    u, v = (float(t) for t in locations[qi, mi, li, pi])
                    wt = float(weights[qi, mi, li, pi])
                    out[qi, mi] += wt * naive_bilinear(img, u, v)
                    mass[qi, mi] += wt * naive_bilinear(ones, u, v)[0]
    return out, mass


def random_inputs(num_images=3, mv=1, m=2, d=3, sizes=((5, 7), (3, 4)), q=6, p=3, dtype=F64, seed=0, spread=0.3):
    g = torch.Generator().manual_seed(seed)
    values = [torch.randn(num_images, mv, d, h, w, generator=g, dtype=dtype) for h, w in sizes]
    locations = (torch.rand(q, m, len(sizes), p, 2, generator=g, dtype=dtype) * (1 + 2 * spread) - spread)
    weights = torch.rand(q, m, len(sizes), p, generator=g, dtype=dtype)
    image_index = torch.randint(0, num_images, (q,), generator=g)
    return values, image_index, locations, weights


def grads_of(values, image_index, locations, weights, method, dtype=F64):
    """Outputs and the gradients of a weighted sum of (out, mass) w.r.t. every float input."""
    vals = [v.detach().clone().requires_grad_(True) for v in values]
    loc = locations.detach().clone().requires_grad_(True)
    wt = weights.detach().clone().requires_grad_(True)
    out, mass = ms_deform_sample(vals, image_index, loc, wt, method=method, return_mass=True)
    g = torch.Generator().manual_seed(7)
    go = torch.randn(out.shape, generator=g, dtype=dtype).to(out.device)
    gm = torch.randn(mass.shape, generator=g, dtype=dtype).to(out.device)
    grads = torch.autograd.grad((out * go).sum() + (mass * gm).sum(), vals + [loc, wt])
    return out.detach(), mass.detach(), grads


# ---------------------------------------------------------------------------------------------------
# bilinear_sample / camera_mean
# ---------------------------------------------------------------------------------------------------
def test_bilinear_sample_matches_naive_loop():
    g = torch.Generator().manual_seed(0)
    b, v, c, h, w, n = 2, 3, 4, 5, 7, 11
    image = torch.randn(b, v, c, h, w, generator=g, dtype=F64)
    uv = torch.rand(n, v, 2, generator=g, dtype=F64) * 1.4 - 0.2
    batch_index = torch.randint(0, b, (n,), generator=g)
    valid = torch.rand(n, v, generator=g) > 0.3
    out = bilinear_sample(image, uv, batch_index, valid)
    expected = torch.zeros(n, v, c, dtype=F64)
    for i in range(n):
        for cam in range(v):
            if valid[i, cam]:
                expected[i, cam] = naive_bilinear(image[batch_index[i], cam], *uv[i, cam].tolist())
    assert out.shape == (n, v, c)
    assert_close(out, expected)
    # 4-d image = one camera
    out4 = bilinear_sample(image[:, 0], uv[:, :1], batch_index)
    assert_close(out4[:, 0], torch.stack([naive_bilinear(image[bi, 0], *uv[i, 0].tolist())
                                          for i, bi in enumerate(batch_index.tolist())]))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_exact_pixel_hit_every_pyramid_level(dtype):
    # A point on the centre of pixel (y, x) of a level returns that pixel (to rounding of u = (x+0.5)/W,
    # hence the dtype tolerance), for every level of a stride 4..64 pyramid of a 128 x 192 image.
    height, width = 128, 192
    g = torch.Generator().manual_seed(1)
    for stride in (4, 8, 16, 32, 64):
        h, w = height // stride, width // stride
        level = torch.randn(2, 3, h, w, generator=g, dtype=dtype)
        ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        ys, xs = ys.flatten(), xs.flatten()
        # the level's pixel centre, written as a full-image pixel coordinate (centre of the stride cell)
        u_img = xs.to(dtype) * stride + (stride - 1) / 2
        v_img = ys.to(dtype) * stride + (stride - 1) / 2
        uv = torch.stack([(u_img + 0.5) / width, (v_img + 0.5) / height], -1)[:, None, :]  # (N, 1, 2)
        bidx = torch.ones(len(xs), dtype=torch.long)
        expected = level[1][:, ys, xs].t()
        assert_close(bilinear_sample(level, uv, bidx)[:, 0], expected, msg=f"stride {stride}")
        for method in ("reference", "fast"):
            o = ms_deform_sample(
                [level[:, None]], bidx, uv.view(-1, 1, 1, 1, 2), torch.ones(len(xs), 1, 1, 1, dtype=dtype),
                method=method,
            )
            assert_close(o[:, 0], expected, msg=f"{method} stride {stride}")


def test_outside_and_invalid_give_zeros_and_no_gradient():
    image = torch.randn(1, 2, 3, 4, 5, dtype=F64, requires_grad=True)
    uv = torch.tensor([[[-0.5, 0.5], [0.5, 0.5]], [[1.3, 0.5], [float("nan"), float("nan")]]], dtype=F64)
    uv.requires_grad_(True)
    valid = torch.tensor([[True, False], [True, False]])
    out = bilinear_sample(image, uv, torch.zeros(2, dtype=torch.long), valid)
    assert torch.equal(out, torch.zeros_like(out))
    out.sum().backward()
    assert torch.equal(image.grad, torch.zeros_like(image))
    assert torch.equal(uv.grad, torch.zeros_like(uv))
    # invalid entries on an image holding inf/NaN stay exact zeros
    bad = torch.full((1, 1, 2, 3, 3), float("nan"))
    out = bilinear_sample(bad, torch.full((1, 1, 2), 0.5), torch.zeros(1, dtype=torch.long), torch.tensor([[False]]))
    assert torch.equal(out, torch.zeros(1, 1, 2))


def test_bilinear_sample_gradcheck():
    g = torch.Generator().manual_seed(2)
    image = torch.randn(2, 2, 2, 4, 5, generator=g, dtype=F64)
    uv = torch.rand(4, 2, 2, generator=g, dtype=F64) * 1.2 - 0.1
    bidx = torch.tensor([0, 1, 1, 0])
    valid = torch.tensor([[True, True], [False, True], [True, False], [True, True]])
    assert gradcheck64(lambda im, p: bilinear_sample(im, p, bidx, valid), (image, uv))


def test_camera_mean_hand_numbers():
    x = torch.tensor([[[1.0, 2.0], [3.0, 6.0], [float("nan"), 0.0]], [[5.0, 5.0], [7.0, 7.0], [9.0, 9.0]]])
    valid = torch.tensor([[True, True, False], [False, False, False]])
    out = camera_mean(x, valid)
    assert torch.equal(out, torch.tensor([[2.0, 4.0], [0.0, 0.0]]))
    with pytest.raises(MSSFError, match="valid"):
        camera_mean(x, valid.float())


# ---------------------------------------------------------------------------------------------------
# ms_deform_sample
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mv", [1, 2])
def test_ms_deform_sample_matches_naive_loop(mv, device):
    values, image_index, locations, weights = random_inputs(mv=mv, m=2)
    expected, expected_mass = naive_ms_deform(values, image_index, locations, weights)
    values, (image_index, locations, weights) = [v.to(device) for v in values], \
        (t.to(device) for t in (image_index, locations, weights))
    for method in ("reference", "fast", "auto"):
        out, mass = ms_deform_sample(values, image_index, locations, weights, method=method, return_mass=True)
        assert out.shape == (6, 2, 3)
        assert_close(out.cpu(), expected, msg=method)
        assert_close(mass.cpu(), expected_mass, msg=method)


def border_locations(sizes, q, m, p, dtype, seed=3):
    """Locations on pixel centres (integer pixel coords), pixel borders, image edges and outside."""
    g = torch.Generator().manual_seed(seed)
    locs = torch.empty(q, m, len(sizes), p, 2, dtype=dtype)
    for li, (h, w) in enumerate(sizes):
        for axis, n in ((0, w), (1, h)):
            # pixel coordinate x = u * n - 0.5 in {-1.5, -1, -0.5, 0, 0.5, ..., n - 0.5, n, n + 0.5}
            px = torch.arange(-3, 2 * n + 2, dtype=dtype) / 2
            pick = px[torch.randint(0, len(px), (q, m, p), generator=g)]
            locs[:, :, li, :, axis] = (pick + 0.5) / n
    return locs


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("mv", [1, 3])
@pytest.mark.parametrize("where", ["random", "borders"])
def test_fast_equals_reference_forward_and_all_gradients(dtype, mv, where, device):
    sizes = ((8, 16), (4, 8), (2, 4))
    values, image_index, locations, weights = random_inputs(
        num_images=3, mv=mv, m=3, d=4, sizes=sizes, q=17, p=2, dtype=dtype, spread=0.4
    )
    if where == "borders":
        locations = border_locations(sizes, 17, 3, 2, dtype)
    values, (image_index, locations, weights) = [v.to(device) for v in values], \
        (t.to(device) for t in (image_index, locations, weights))
    ref = grads_of(values, image_index, locations, weights, "reference", dtype)
    fast = grads_of(values, image_index, locations, weights, "fast", dtype)
    assert_close(fast[0], ref[0], msg="out")
    assert_close(fast[1], ref[1], msg="mass")
    names = [f"values[{i}]" for i in range(len(sizes))] + ["locations", "weights"]
    for name, a, b in zip(names, fast[2], ref[2]):
        assert_close(a, b, msg=f"grad {name}")
    # the comparison is not vacuous: points outside read nothing and some gradients are non-zero
    assert bool((ref[1] != weights.sum((2, 3))).any())
    assert all(bool(gr.abs().sum() > 0) for gr in ref[2])


@pytest.mark.parametrize("method", ["reference", "fast"])
@pytest.mark.parametrize("mv", [1, 2])
def test_ms_deform_sample_gradcheck(method, mv):
    values, image_index, locations, weights = random_inputs(
        num_images=2, mv=mv, m=2, d=2, sizes=((3, 4), (2, 2)), q=3, p=2, seed=4
    )

    def fn(v0, v1, loc, wt):
        out, mass = ms_deform_sample([v0, v1], image_index, loc, wt, method=method, return_mass=True)
        return out, mass

    assert gradcheck64(fn, (values[0], values[1], locations, weights))


def test_mass_equals_sampling_a_ones_map():
    values, image_index, locations, weights = random_inputs(mv=1, m=2, spread=0.5, seed=5)
    ones = [torch.ones(v.shape[0], 1, 1, *v.shape[-2:], dtype=F64) for v in values]
    expected = ms_deform_sample(ones, image_index, locations, weights, method="reference")[..., 0]
    _, mass = ms_deform_sample(values, image_index, locations, weights, method="fast", return_mass=True)
    assert_close(mass, expected)
    # hand-worked: all points inside -> mass = sum of weights; one point a quarter outside a corner
    v = [torch.randn(1, 1, 1, 4, 4, dtype=F64)]
    loc = torch.tensor([0.5, 0.5, 0.0, 0.0], dtype=F64).view(1, 1, 1, 2, 2)  # centre; corner u=v=0
    wt = torch.tensor([0.25, 0.5], dtype=F64).view(1, 1, 1, 2)
    for method in ("reference", "fast"):
        _, mass = ms_deform_sample(v, torch.tensor([0]), loc, wt, method=method, return_mass=True)
        assert_close(mass, torch.tensor([[0.25 + 0.5 * 0.25]], dtype=F64))


@pytest.mark.parametrize("method", ["reference", "fast"])
def test_empty_queries_forward_and_backward(method):
    values, _, _, _ = random_inputs(mv=2, m=2)
    values = [v.requires_grad_(True) for v in values]
    loc = torch.zeros(0, 2, 2, 3, 2, dtype=F64, requires_grad=True)
    wt = torch.zeros(0, 2, 2, 3, dtype=F64, requires_grad=True)
    out, mass = ms_deform_sample(values, torch.zeros(0, dtype=torch.long), loc, wt, method=method, return_mass=True)
    assert out.shape == (0, 2, 3) and mass.shape == (0, 2)
    (out.sum() + mass.sum()).backward()
    assert loc.grad.shape == loc.shape and wt.grad.shape == wt.shape
    assert all(v.grad is None or torch.equal(v.grad, torch.zeros_like(v)) for v in values)


@pytest.mark.parametrize("method", ["reference", "fast"])
def test_batch_independence(method):
    values, image_index, locations, weights = random_inputs(num_images=3, mv=2, m=2, q=20, seed=6)
    base = ms_deform_sample(values, image_index, locations, weights, method=method)
    for j in range(3):
        changed = [v.clone() for v in values]
        for v in changed:
            v[j] = torch.randn_like(v[j]) * 100
        out = ms_deform_sample(changed, image_index, locations, weights, method=method)
        others = image_index != j
        assert torch.equal(out[others], base[others])
        assert not torch.equal(out[~others], base[~others])
    # the same for bilinear_sample (batch b of a 2-camera image)
    image = values[0][:, :2].reshape(3, 2, 3, 5, 7)  # (B=3, V=2, C=3, H, W)
    uv = locations[:, 0, 0, :2]  # (N=20, V=2, 2)
    base = bilinear_sample(image, uv, image_index)
    changed = image.clone()
    changed[1] = 50.0
    out = bilinear_sample(changed, uv, image_index)
    assert torch.equal(out[image_index != 1], base[image_index != 1])


def test_fast_reads_channels_last_values_without_copy_and_agrees():
    values, image_index, locations, weights = random_inputs(mv=1, m=2, d=5)
    cl = []
    for v in values:  # channels-last storage, viewed as (I, 1, D, H, W)
        x = v[:, 0].contiguous(memory_format=torch.channels_last)
        cl.append(x.view(x.shape[0], 1, *x.shape[1:]))
    assert cl[0].permute(0, 1, 3, 4, 2).is_contiguous()
    assert_close(
        ms_deform_sample(cl, image_index, locations, weights, method="fast"),
        ms_deform_sample(values, image_index, locations, weights, method="reference"),
    )


def test_bad_inputs_raise_named_errors():
    values, image_index, locations, weights = random_inputs(num_images=3, mv=1, m=2)
    call = lambda **kw: ms_deform_sample(  # noqa: E731
        kw.get("values", values), kw.get("image_index", image_index), kw.get("locations", locations),
        kw.get("weights", weights), method=kw.get("method", "auto"),
    )
    with pytest.raises(MSSFError, match=r"values\[1\]"):
        call(values=[values[0], values[1][:2]])  # different I
    with pytest.raises(MSSFError, match=r"values\[1\]"):
        call(values=[values[0], torch.randn(3, 1, 4, 3, 4, dtype=F64)])  # different D
    with pytest.raises(MSSFError, match="values"):
        call(values=values[0])
    with pytest.raises(MSSFError, match="Mv"):
        call(values=[torch.randn(3, 3, 3, 5, 7, dtype=F64), torch.randn(3, 3, 3, 3, 4, dtype=F64)])
    with pytest.raises(MSSFError, match="locations"):
        call(locations=locations[..., :1])
    with pytest.raises(MSSFError, match="locations"):
        call(locations=locations[:, :, :1])  # L mismatch with values
    with pytest.raises(MSSFError, match="weights"):
        call(weights=weights[:, :, :, :1])
    with pytest.raises(MSSFError, match="image_index"):
        call(image_index=torch.tensor([0, 1, 2, 3, 0, 0]))
    with pytest.raises(MSSFError, match="image_index"):
        call(image_index=image_index.float())
    with pytest.raises(MSSFError, match="locations"):
        bad = locations.clone()
        bad[0, 0, 0, 0, 0] = float("nan")
        call(locations=bad)
    with pytest.raises(MSSFError, match="locations"):
        call(locations=locations.float())
    with pytest.raises(MSSFError, match="method"):
        call(method="cuda")
    with pytest.raises(MSSFError, match="image"):
        bilinear_sample(torch.randn(2, 3, 4), torch.rand(1, 1, 2), torch.zeros(1, dtype=torch.long))
    with pytest.raises(MSSFError, match="batch_index"):
        bilinear_sample(torch.randn(2, 3, 4, 5), torch.rand(1, 1, 2), torch.tensor([2]))
    with pytest.raises(MSSFError, match="uv"):
        bilinear_sample(torch.randn(2, 2, 3, 4, 5), torch.rand(1, 3, 2), torch.tensor([0]))
    with pytest.raises(MSSFError, match="uv"):
        bilinear_sample(torch.randn(1, 3, 4, 5), torch.full((1, 1, 2), float("nan")), torch.tensor([0]))


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
    from mssf_blocks.functional import touched as sampling

    if branch == "auto":
        return ms_deform_sample_project(values, image_index, locations, weights, proj_w, proj_b, method="touched")
    return sampling._ms_deform_sample_touched(values, image_index, locations, weights, proj_w, proj_b, branch)


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


# ---------------------------------------------------------------------------------------------------
# bilinear_sample methods: "gather" (distinct corner pixels + embedding_bag) vs "grid" (grid_sample)
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("where", ["random", "borders"])
@pytest.mark.parametrize("layout", ["nchw", "channels_last"])
def test_bilinear_gather_equals_grid_forward_and_gradients(dtype, where, layout):
    g = torch.Generator().manual_seed(15)
    b, v, c, h, w, n = 2, 2, 5, 6, 9, 23
    image = torch.randn(b, v, c, h, w, generator=g, dtype=dtype)
    if where == "borders":  # pixel centres, pixel borders, image edges and outside
        uv = border_locations(((h, w),), n, v, 1, dtype, seed=16)[:, :, 0, 0]  # (N, V, 2)
    else:
        uv = torch.rand(n, v, 2, generator=g, dtype=dtype) * 1.4 - 0.2
    uv[0, 0] = float("nan")  # invalid entries may hold anything
    batch_index = torch.randint(0, b, (n,), generator=g)
    valid = torch.rand(n, v, generator=g) > 0.2
    valid[0, 0] = False
    go = torch.randn(n, v, c, generator=g, dtype=dtype)
    results = {}
    for method in ("gather", "grid", "auto"):
        im = image.detach().clone().requires_grad_(True)
        feed = im
        if layout == "channels_last":
            feed = im.reshape(b * v, c, h, w).contiguous(memory_format=torch.channels_last).view(b, v, c, h, w)
        p = uv.detach().clone().requires_grad_(True)
        out = bilinear_sample(feed, p, batch_index, valid, method=method)
        gi, gp = torch.autograd.grad((out * go).sum(), (im, p))
        results[method] = (out.detach(), gi, gp)
    # independent naive loop for the forward
    expected = torch.zeros(n, v, c, dtype=F64)
    for i in range(n):
        for cam in range(v):
            if valid[i, cam]:
                expected[i, cam] = naive_bilinear(image[batch_index[i], cam].double(), *uv[i, cam].double().tolist())
    for method in ("gather", "auto"):
        for name, a, ref in zip(("out", "grad image", "grad uv"), results[method], results["grid"]):
            assert_close(a, ref, msg=f"{method} {name}")
    assert_close(results["gather"][0], expected)
    assert results["grid"][1].abs().sum() > 0 and results["grid"][2].abs().sum() > 0
    assert torch.equal(results["gather"][2][0, 0], torch.zeros(2, dtype=dtype))  # invalid: no gradient


@pytest.mark.parametrize("method", ["gather", "grid"])
def test_bilinear_sample_methods_gradcheck(method):
    g = torch.Generator().manual_seed(17)
    image = torch.randn(2, 2, 2, 4, 5, generator=g, dtype=F64)
    uv = torch.rand(6, 2, 2, generator=g, dtype=F64) * 1.2 - 0.1
    bidx = torch.tensor([0, 1, 1, 0, 0, 1])
    valid = torch.tensor([[True, True], [False, True], [True, False], [True, True], [True, True], [True, False]])
    assert gradcheck64(lambda im, p: bilinear_sample(im, p, bidx, valid, method=method), (image, uv))
    with pytest.raises(MSSFError, match="method"):
        bilinear_sample(image, uv, bidx, valid, method="fast")
