"""spconv's CPU sparse convolutions against a dense ``F.conv3d``, as the README states them.

README.md says what holds for spconv 2.3 on a CPU-only torch: ``SubMConv3d`` and ``SparseConv3d`` give
the dense convolution's values at their output sites in float32 and float64, with and without bias,
forward and backward (input features, weight, bias), once ``enable_cpu_backward()`` is called. The
reference scatters the features into a dense grid, runs ``F.conv3d`` and reads the output sites spconv
reports (for ``SubMConv3d``: the input sites); gradients of a random linear loss through both.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

sp = pytest.importorskip("spconv.pytorch")
from mssf_blocks.integrations.spconv import enable_cpu_backward  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")

GRID = (8, 12, 10)


@pytest.mark.parametrize("kind", ["subm", "sparse"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["float32", "float64"])
@pytest.mark.parametrize("bias", [False, True], ids=["no_bias", "bias"])
def test_sparse_conv_equals_dense_conv3d(kind, dtype, bias):
    enable_cpu_backward()
    gen = torch.Generator().manual_seed(7)
    occupied = torch.rand(GRID, generator=gen) < 0.15
    sites = occupied.nonzero()  # (N, 3): z, y, x
    coords = torch.cat([torch.zeros(len(sites), 1, dtype=torch.int64), sites], 1).int()
    feats = torch.randn(len(sites), 3, generator=gen, dtype=dtype).requires_grad_(True)
    cls = sp.SubMConv3d if kind == "subm" else sp.SparseConv3d
    conv = cls(3, 4, 3, padding=1, bias=bias, indice_key="k").to(dtype)
    with torch.no_grad():
        conv.weight.copy_(torch.randn(conv.weight.shape, generator=gen, dtype=dtype))
        if bias:
            conv.bias.copy_(torch.randn(4, generator=gen, dtype=dtype))
    out = conv(sp.SparseConvTensor(feats, coords, list(GRID), 1))
    g = torch.randn(out.features.shape, generator=gen, dtype=dtype)
    got = torch.autograd.grad(out.features, [feats, conv.weight] + ([conv.bias] if bias else []), g)

    # the reference: the same parameters as leaves, spconv's weight layout (O, kz, ky, kx, C) -> (O, C, k, k, k)
    f_ref = feats.detach().clone().requires_grad_(True)
    w_ref = conv.weight.detach().clone().requires_grad_(True)
    b_ref = conv.bias.detach().clone().requires_grad_(True) if bias else None
    dense = torch.zeros(1, 3, *GRID, dtype=dtype).permute(0, 2, 3, 4, 1).index_put(
        (torch.zeros(len(sites), dtype=torch.long), sites[:, 0], sites[:, 1], sites[:, 2]), f_ref).permute(0, 4, 1, 2, 3)
    ref_full = F.conv3d(dense, w_ref.permute(0, 4, 1, 2, 3), b_ref, padding=1)
    at = out.indices.long()
    # the output sites: the input sites (submanifold), or every site with an input in its 3^3 window
    sites_out = occupied if kind == "subm" else F.max_pool3d(occupied[None, None].float(), 3, 1, 1)[0, 0] > 0
    assert sorted(map(tuple, at[:, 1:].tolist())) == sorted(map(tuple, sites_out.nonzero().tolist()))
    ref = ref_full[0, :, at[:, 1], at[:, 2], at[:, 3]].T
    want = torch.autograd.grad(ref, [f_ref, w_ref] + ([b_ref] if bias else []), g)

    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == torch.float64 else {"atol": 1e-4, "rtol": 1e-4}
    torch.testing.assert_close(out.features, ref, **tol)
    for name, a, b in zip(("features", "weight", "bias"), got, want):
        torch.testing.assert_close(a, b, **tol, msg=lambda m, n=name: f"gradient of {n}: {m}")
