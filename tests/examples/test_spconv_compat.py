"""spconv layers train on CPU after enable_cpu_backward, with gradients equal to a dense conv3d."""

import pytest
import torch
import torch.nn.functional as F

spconv = pytest.importorskip("spconv.pytorch")

from mssf_examples.spconv_compat import enable_cpu_backward  # noqa: E402


@pytest.mark.parametrize("kind", ["sparse", "subm"])
def test_spconv_gradients_equal_dense_reference(kind):
    assert enable_cpu_backward()
    torch.manual_seed(0)
    coords = torch.unique(torch.randint(0, 6, (60, 3)), dim=0)
    coords = torch.cat([torch.zeros(len(coords), 1, dtype=torch.long), coords], 1).int()
    stride = 2 if kind == "sparse" else 1
    conv = (spconv.SparseConv3d(3, 4, 3, stride=2, padding=1, bias=False) if kind == "sparse"
            else spconv.SubMConv3d(3, 4, 3, padding=1, bias=False))
    f = torch.randn(len(coords), 3, requires_grad=True)
    out = conv(spconv.SparseConvTensor(f, coords, [6, 6, 6], 1))
    g = torch.randn_like(out.features)
    (out.features * g).sum().backward()

    # Dense reference: scatter to a grid, conv3d (spconv weight layout is (out, kz, ky, kx, in)).
    f2 = f.detach().clone().requires_grad_(True)
    w = conv.weight.detach().clone().requires_grad_(True)
    c = coords.long()
    dense = torch.zeros(1, 6, 6, 6, 3).index_put((c[:, 0], c[:, 1], c[:, 2], c[:, 3]), f2).permute(0, 4, 1, 2, 3)
    y = F.conv3d(dense, w.permute(0, 4, 1, 2, 3), stride=stride, padding=1)
    oc = out.indices.long()
    y_rows = y[oc[:, 0], :, oc[:, 1], oc[:, 2], oc[:, 3]]
    torch.testing.assert_close(out.features, y_rows, rtol=1e-5, atol=1e-5)
    (y_rows * g).sum().backward()
    torch.testing.assert_close(f.grad, f2.grad, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(conv.weight.grad, w.grad, rtol=1e-5, atol=1e-5)
