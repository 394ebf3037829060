"""The sampling op's kept graphs (``functional/deform/kept.py``): under ``torch.compile`` with gradients the
CPU backends run their forward once, under autograd, and the backward differentiates that graph instead of
running the forward again. Checked: one forward per training step (a spy on the backend), every gradient
equal to the float64 reference's, nothing left waiting after the backward or after a dropped forward, and
the recomputing fallback (graph evicted, or made for other inputs) with the same numbers."""

from __future__ import annotations

import gc
import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks import torch_versions as _compat
from mssf_blocks.functional.deform import kept
from mssf_blocks.functional.deform import op as sampling_op
from mssf_blocks.functional.deform.op import deform_sample_project

sys.path.insert(0, str(Path(__file__).parent))
from test_sampling_op import inputs, naive_project, reference_grads, with_grad  # noqa: E402

pytestmark = [
    pytest.mark.usefixtures("one_thread"),
    pytest.mark.skipif(_compat.missing("custom_op") is not None, reason=_compat.missing("custom_op") or ""),
]


def _spy(monkeypatch, backend):
    calls = []
    fn = sampling_op._OP_BACKENDS[backend]
    monkeypatch.setitem(sampling_op._OP_BACKENDS, backend, lambda *a: calls.append(torch.is_grad_enabled()) or fn(*a))
    return calls


def _check_grads(args, targs, grad):
    ref_levels, *ref_rest = reference_grads(args, grad)
    for got, want in zip(targs[0], ref_levels):
        torch.testing.assert_close(got.grad, want, atol=1e-10, rtol=1e-8)
    for t, want, name in zip(targs[2:], ref_rest, ("locations", "weights", "proj_weight", "proj_bias")):
        torch.testing.assert_close(t.grad, want, atol=1e-10, rtol=1e-8, msg=name)


@pytest.mark.parametrize("backend", ["touched", "grid"])
def test_keep_op_runs_the_forward_once_and_matches_the_reference(monkeypatch, backend):
    args = inputs(seed=3)
    calls = _spy(monkeypatch, backend)
    targs = with_grad(args)
    out, key = torch.ops.mssf_blocks.deform_sample_project_keep(*targs, backend, True, True)
    assert key.dtype == torch.int64 and key.dim() == 0 and kept.waiting() == 1
    torch.testing.assert_close(out, naive_project(*args), atol=1e-12, rtol=1e-10)
    grad = torch.randn(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    out.backward(grad)
    assert calls == [True]  # one forward, under autograd; the backward took its graph
    assert kept.waiting() == 0
    _check_grads(args, targs, grad)


def test_the_key_is_a_cpu_tensor_for_inputs_on_any_device():
    """The fake implementation must give the key the device the real one does (the CPU), also for CUDA
    inputs (the grid backend serves CUDA without triton); meta inputs run the fake implementation."""
    values, image_index, locations, weights, proj_w, proj_b = (
        [t.to("meta") for t in a] if isinstance(a, list) else a.to("meta") for a in inputs(seed=5))
    out, key = torch.ops.mssf_blocks.deform_sample_project_keep(values, image_index, locations, weights, proj_w, proj_b,
                                                                "grid", True, True)
    assert out.device.type == "meta" and out.shape == (7, 2, 3)
    assert key.device.type == "cpu" and key.dtype == torch.int64 and key.dim() == 0
    _, real_key = torch.ops.mssf_blocks.deform_sample_project_keep(*with_grad(inputs(seed=5)), "grid", True, True)
    assert real_key.device == key.device


@pytest.mark.parametrize("why", ["evicted", "other_inputs"])
def test_backward_recomputes_when_no_graph_fits(monkeypatch, why):
    args = inputs(seed=4)
    calls = _spy(monkeypatch, "touched")
    targs = with_grad(args)
    # "other_inputs": a graph made for frozen levels and projection cannot serve a backward that needs them
    flags = (True, True) if why == "evicted" else (False, False)
    out, _ = torch.ops.mssf_blocks.deform_sample_project_keep(*targs, "touched", *flags)
    if why == "evicted":
        monkeypatch.setattr(kept, "MAX_KEPT", 0)
        kept.keep(out, [], None)  # (a newer graph pushes it out)
    grad = torch.randn(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    out.backward(grad)
    assert calls == [True, True]  # the forward again, in the backward
    _check_grads(args, targs, grad)
    gc.collect()
    assert kept.waiting() == 0


@pytest.mark.skipif(_compat.missing("compile_dynamic") is not None, reason=_compat.missing("compile_dynamic") or "")
def test_compiled_training_keeps_one_forward_per_step_and_frees_dropped_graphs(monkeypatch):
    calls = _spy(monkeypatch, "touched")

    def run(values, image_index, locations, weights, proj_w, proj_b):
        return deform_sample_project(values, image_index, locations, weights, proj_w, proj_b, backend="touched")

    compiled = torch.compile(run, fullgraph=True, dynamic=True, backend="aot_eager")
    for q in (7, 9):
        args = inputs(seed=q, q=q)
        targs = with_grad(args)
        calls.clear()
        out = compiled(*targs)
        grad = torch.randn(out.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(q))
        out.backward(grad)
        assert calls == [True], calls  # (fake-tensor tracing calls no backend)
        assert kept.waiting() == 0
        torch.testing.assert_close(out, naive_project(*args), atol=1e-12, rtol=1e-10)
        _check_grads(args, targs, grad)
    out = compiled(*with_grad(inputs(seed=11, q=11)))  # a forward whose graph is dropped without a backward
    assert kept.waiting() == 1
    del out
    gc.collect()
    assert kept.waiting() == 0
    with torch.no_grad():  # no gradients: the plain op, nothing kept
        compiled(*inputs(seed=12, q=12))
    assert kept.waiting() == 0
