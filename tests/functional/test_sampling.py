"""Tests of ``mssf_blocks.functional.sampling.ms_deform_sample`` (every method) against naive loops and
hand-worked numbers, gradients included. ``bilinear_sample`` / ``camera_mean``: ``test_bilinear_sample.py``;
``ms_deform_sample_project``: ``test_deform_project.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.sampling import bilinear_sample, ms_deform_sample
from mssf_blocks.testing import assert_close, gradcheck64

sys.path.insert(0, str(Path(__file__).parent))
from sampling_references import F64, border_locations, naive_ms_deform, random_inputs  # noqa: E402


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
