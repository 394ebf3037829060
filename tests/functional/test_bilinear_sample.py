"""Tests of ``mssf_blocks.functional.sampling.bilinear_sample`` (both methods) and ``camera_mean`` against
naive loops, ``grid_sample`` and hand-worked numbers. ``ms_deform_sample``: ``test_sampling.py``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.sampling import bilinear_sample, camera_mean, ms_deform_sample
from mssf_blocks.testing import assert_close, gradcheck64

sys.path.insert(0, str(Path(__file__).parent))
from sampling_references import F64, border_locations, naive_bilinear  # noqa: E402


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
# bilinear_sample methods: "gather" (distinct corner pixels + embedding_bag) vs "grid" (grid_sample)
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("where", ["random", "borders"])
@pytest.mark.parametrize("layout", ["nchw", "channels_last"])
@pytest.mark.parametrize("v", [1, 2])
def test_bilinear_gather_equals_grid_forward_and_gradients(dtype, where, layout, v):
    g = torch.Generator().manual_seed(15)
    b, c, h, w, n = 2, 5, 6, 9, 23
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
