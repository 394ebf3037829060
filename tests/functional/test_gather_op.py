"""``bilinear_sample`` under ``torch.compile`` on the CPU: the eager gather as one opaque op
(``functional/deform/gather_op.py``) instead of the static grid formulation. Checked against torch's own
``F.grid_sample`` per point in float64 (outputs and the gradients of image and points): with and
without gradients, several cameras with invalid entries, no recompile across point counts, the op in
the captured graph, one forward per training step (the backward differentiates the kept graph), nothing
left waiting; exporters keep the grid formulation."""

from __future__ import annotations

import gc

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks import torch_versions as _compat
from mssf_blocks.functional.deform import gather_op, kept, touched
from mssf_blocks.functional.sampling import bilinear_sample

torch._dynamo = pytest.importorskip("torch._dynamo")
from torch._dynamo.testing import CompileCounterWithBackend  # noqa: E402

_MISSING = _compat.missing("compile_dynamic") or _compat.missing("custom_op")
pytestmark = [pytest.mark.usefixtures("one_thread"), pytest.mark.skipif(_MISSING is not None, reason=str(_MISSING))]
F64 = torch.float64


def _reference(image, uv, batch_index, valid):
    """``(N, V, C)`` by ``F.grid_sample`` one point at a time (align_corners=False, zero padding)."""
    n, v = valid.shape
    rows = []
    for i in range(n):
        cams = []
        for cam in range(v):
            img = image[batch_index[i], cam][None]  # (1, C, H, W)
            g = (2 * uv[i, cam] - 1).view(1, 1, 1, 2)
            s = F.grid_sample(img, g, mode="bilinear", padding_mode="zeros", align_corners=False)[0, :, 0, 0]
            cams.append(s if valid[i, cam] else torch.zeros_like(s))
        rows.append(torch.stack(cams))
    return torch.stack(rows)


def _case(n, seed, v=2):
    g = torch.Generator().manual_seed(seed)
    image = torch.randn(2, v, 5, 6, 11, generator=g, dtype=F64)  # (no size equal to a point count)
    uv = torch.rand(n, v, 2, generator=g, dtype=F64) * 1.3 - 0.15  # some corners outside the map
    batch_index = torch.randint(0, 2, (n,), generator=g)
    valid = torch.rand(n, v, generator=g) > 0.25
    return image, uv, batch_index, valid


def _sample(image, uv, batch_index, valid):
    return bilinear_sample(image, uv, batch_index, valid)


@pytest.mark.parametrize("backend", ["eager", "aot_eager"])
def test_compiled_bilinear_sample_is_the_op_and_matches_grid_sample(monkeypatch, backend):
    forwards = []
    fn = touched.sample_points
    monkeypatch.setattr(touched, "sample_points", lambda *a: forwards.append(torch.is_grad_enabled()) or fn(*a))
    torch._dynamo.reset()
    counter = CompileCounterWithBackend(backend)
    compiled = torch.compile(_sample, fullgraph=True, dynamic=True, backend=counter)
    frames = []
    for n in (9, 17, 30):
        image, uv, batch_index, valid = _case(n, seed=n)
        image.requires_grad_(), uv.requires_grad_()
        forwards.clear()
        out = compiled(image, uv, batch_index, valid)
        assert len(forwards) == 2  # one gather per camera, nothing else sampled
        ref_image, ref_uv = image.detach().clone().requires_grad_(), uv.detach().clone().requires_grad_()
        ref = _reference(ref_image, ref_uv, batch_index, valid)
        torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-10)
        grad = torch.randn(out.shape, dtype=F64, generator=torch.Generator().manual_seed(n))
        out.backward(grad)
        ref.backward(grad)
        assert len(forwards) == 2  # the backward differentiated the forward's kept graph: no second forward
        torch.testing.assert_close(image.grad, ref_image.grad, atol=1e-12, rtol=1e-10)
        torch.testing.assert_close(uv.grad, ref_uv.grad, atol=1e-12, rtol=1e-10)
        frames.append(counter.frame_count)
    assert frames == [1, 1, 1], frames  # one graph for every point count
    gc.collect()
    assert kept.waiting() == 0


def test_compiled_bilinear_sample_without_gradients():
    torch._dynamo.reset()
    graphs = []

    def backend(gm, example_inputs):
        graphs.append({str(node.target) for node in gm.graph.nodes if node.op == "call_function"})
        return gm.forward

    compiled = torch.compile(_sample, fullgraph=True, dynamic=True, backend=backend)
    image, uv, batch_index, valid = _case(13, seed=1, v=1)
    with torch.no_grad():
        out = compiled(image, uv, batch_index, valid)
    torch.testing.assert_close(out, _reference(image, uv, batch_index, valid), atol=1e-12, rtol=1e-10)
    assert any("bilinear_gather" in t for t in graphs[0]) and not any("grid_sampler" in t for t in graphs[0])
    assert kept.waiting() == 0


def test_outside_torch_compile_the_op_is_not_taken():
    # eager keeps its own path; exporters (torch.export, ONNX) keep the grid formulation (compiled_gather is
    # False while exporting: torch_versions.is_exporting)
    assert not gather_op.compiled_gather("cpu")
    assert not gather_op.compiled_gather("cuda")
