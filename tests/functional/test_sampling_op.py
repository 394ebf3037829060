"""The sampling op (``torch.ops.mssf_blocks.deform_sample_project``) on the CPU: every CPU backend against
float64 loops, ``opcheck``, the skipped value gradient, backend forcing (argument, environment), the
clear error for Triton on CPU tensors, the warn-once fallback to the grid path, compile and export.
The Triton backend's numbers are checked under the interpreter (``test_triton_kernels.py``)."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import pytest
import torch

from mssf_blocks import torch_versions as _compat
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.deform import op as sampling_op
from mssf_blocks.functional.plan_costs import SAMPLING_BACKENDS
from mssf_blocks.functional import bilinear_sample, ms_deform_sample_project, ms_deform_sample_reference
from mssf_blocks.functional.deform.op import deform_sample_project, resolve_backend

sys.path.insert(0, str(Path(__file__).parent))
from sampling_references import naive_ms_deform, random_inputs  # noqa: E402

#: the registered op (torch.ops.mssf_blocks...) needs torch.library.custom_op; on an older torch the entry
#: calls the backends as plain functions (the tests of deform_sample_project still run there)
_NO_OP = _compat.missing("custom_op")
needs_op = pytest.mark.skipif(_NO_OP is not None, reason=_NO_OP or "")

F64 = torch.float64
pytestmark = pytest.mark.usefixtures("one_thread")


def inputs(seed=0, q=7, m=2, d=3, c=4, sizes=((5, 6), (3, 4)), p=2, num_images=2):
    values, image_index, locations, weights = random_inputs(num_images=num_images, mv=1, m=m, d=c, sizes=sizes, q=q,
                                                            p=p, seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    proj_w = torch.randn(m, d, c, generator=g, dtype=F64)
    proj_b = torch.randn(m, d, generator=g, dtype=F64)
    return values, image_index, locations, weights, proj_w, proj_b


def naive_project(values, image_index, locations, weights, proj_w, proj_b):
    """Naive loops: sample the raw channels per head, project with the head's rows, bias times the mass."""
    sampled, mass = naive_ms_deform(values, image_index, locations, weights)
    return torch.einsum("qmc,mdc->qmd", sampled, proj_w) + mass[..., None] * proj_b


def reference_grads(args, grad):
    """Float64 gradients of every input through the grid_sample reference (autograd), projection after."""
    values, image_index, locations, weights, proj_w, proj_b = args
    vals = [v.detach().clone().requires_grad_() for v in values]
    loc, wt, pw, pb = (t.detach().clone().requires_grad_() for t in (locations, weights, proj_w, proj_b))
    sampled, mass = ms_deform_sample_reference(vals, image_index, loc, wt, return_mass=True)
    out = torch.einsum("qmc,mdc->qmd", sampled, pw) + mass[..., None] * pb
    out.backward(grad)
    return [v.grad for v in vals], loc.grad, wt.grad, pw.grad, pb.grad


def with_grad(args):
    values, image_index, locations, weights, proj_w, proj_b = args
    return ([v.detach().clone().requires_grad_() for v in values], image_index,
            *(t.detach().clone().requires_grad_() for t in (locations, weights, proj_w, proj_b)))


@pytest.mark.parametrize("backend", ["touched", "grid"])
@pytest.mark.parametrize("through_op", [False, pytest.param(True, marks=needs_op)])
def test_cpu_backends_match_float64_loops_with_gradients(backend, through_op):
    """Both the entry (native autograd) and the registered op (explicit backward op) paths."""
    args = inputs()
    ref = naive_project(*args)
    grad = torch.randn(ref.shape, dtype=F64, generator=torch.Generator().manual_seed(9))
    ref_grads = reference_grads(args, grad)
    targs = with_grad(args)
    if through_op:
        out = torch.ops.mssf_blocks.deform_sample_project(*targs, backend)
    else:
        out = deform_sample_project(*targs, backend=backend)
    torch.testing.assert_close(out, ref, atol=1e-12, rtol=1e-10)
    out.backward(grad)
    got = [v.grad for v in targs[0]], *(t.grad for t in targs[2:])
    for g, want in zip(got[0], ref_grads[0]):
        torch.testing.assert_close(g, want, atol=1e-10, rtol=1e-8)
    for g, want, name in zip(got[1:], ref_grads[1:], ("locations", "weights", "proj_weight", "proj_bias")):
        torch.testing.assert_close(g, want, atol=1e-10, rtol=1e-8, msg=name)


@needs_op
@pytest.mark.parametrize("backend", ["touched", "grid"])
def test_opcheck(backend):
    targs = with_grad(inputs(seed=1))
    torch.library.opcheck(torch.ops.mssf_blocks.deform_sample_project.default, (*targs, backend))


@needs_op
def test_value_gradient_skipped_when_the_values_need_none():
    """A frozen image branch: no gradient for values / projection, the location and weight gradients as
    the reference's."""
    args = inputs(seed=2)
    values, image_index, locations, weights, proj_w, proj_b = args
    loc, wt = locations.clone().requires_grad_(), weights.clone().requires_grad_()
    out = torch.ops.mssf_blocks.deform_sample_project(values, image_index, loc, wt, proj_w, proj_b, "grid")
    grad = torch.randn(out.shape, dtype=F64, generator=torch.Generator().manual_seed(4))
    out.backward(grad)
    _, ref_loc, ref_wt, _, _ = reference_grads(args, grad)
    torch.testing.assert_close(loc.grad, ref_loc, atol=1e-10, rtol=1e-8)
    torch.testing.assert_close(wt.grad, ref_wt, atol=1e-10, rtol=1e-8)
    assert all(v.grad is None for v in values) and proj_w.grad is None


def test_backend_table_and_forcing(monkeypatch):
    monkeypatch.delenv(sampling_op.ENV_VAR, raising=False)
    assert SAMPLING_BACKENDS["cpu"] == "touched"
    assert resolve_backend("auto", "cpu", torch.float32, 32) == "touched"
    assert resolve_backend("grid", "cpu", torch.float32, 32) == "grid"
    assert resolve_backend("auto", "xpu", torch.float32, 32) == "grid"  # no entry: the fallback
    monkeypatch.setenv(sampling_op.ENV_VAR, "grid")
    assert resolve_backend("auto", "cpu", torch.float32, 32) == "grid"
    assert resolve_backend("touched", "cpu", torch.float32, 32) == "touched"  # the argument wins
    monkeypatch.setenv(sampling_op.ENV_VAR, "fastest")
    with pytest.raises(MSSFError, match=r"\$MSSF_SAMPLING_BACKEND: expected 'auto' or one of .* got 'fastest'"):
        resolve_backend("auto", "cpu", torch.float32, 32)
    monkeypatch.delenv(sampling_op.ENV_VAR)
    with pytest.raises(MSSFError, match="backend: expected 'auto' or one of"):
        deform_sample_project(*inputs(), backend="cuda")


def test_triton_forced_on_cpu_tensors_without_the_interpreter_is_a_clear_error(monkeypatch):
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    with pytest.raises(MSSFError, match=r"backend: 'triton' cannot serve these inputs: CPU tensors need .*TRITON_INTERPRET"):
        deform_sample_project(*inputs(), backend="triton")
    monkeypatch.setenv("TRITON_INTERPRET", "1")
    with pytest.raises(MSSFError, match=r"'triton' cannot serve these inputs: the kernels take .* got torch.float64"):
        deform_sample_project(*inputs(), backend="triton")


@needs_op
def test_triton_failure_warns_once_and_falls_back_to_grid(monkeypatch):
    """A launch that fails (here: a broken backend module) warns once, naming the cause; the grid path
    serves this and every later call, with the grid path's numbers."""
    from mssf_blocks.functional.deform.triton import launch as triton_backend  # (imports triton: the dev extra has it)

    def broken(*args, **kwargs):
        raise RuntimeError("ptxas exited with status 255")

    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    monkeypatch.setattr(triton_backend, "forward", broken)
    monkeypatch.setattr(sampling_op, "_TRITON_FAILURE", [])
    args = inputs(seed=3)
    with pytest.warns(RuntimeWarning, match="Triton sampling kernels failed .*ptxas exited with status 255.*grid"):
        out = torch.ops.mssf_blocks.deform_sample_project(*args, "triton")
    torch.testing.assert_close(out, naive_project(*args), atol=1e-12, rtol=1e-10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        torch.ops.mssf_blocks.deform_sample_project(*args, "triton")  # no second warning
    assert resolve_backend("auto", "cuda", torch.float32, 32) == "grid"  # auto no longer picks it


def test_bad_inputs_name_the_argument():
    values, image_index, locations, weights, proj_w, proj_b = inputs()
    with pytest.raises(MSSFError, match="proj_weight"):
        deform_sample_project(values, image_index, locations, weights, proj_w[:, :, :2], proj_b)
    with pytest.raises(MSSFError, match="values: expected raw levels"):
        deform_sample_project([v.expand(-1, 2, -1, -1, -1) for v in values], image_index, locations, weights,
                              proj_w, proj_b)
    with pytest.raises(MSSFError, match="image_index"):
        deform_sample_project(values, image_index + 5, locations, weights, proj_w, proj_b)


@needs_op
@pytest.mark.skipif(_compat.missing("compile_dynamic") is not None, reason=_compat.missing("compile_dynamic") or "")
def test_op_compiles_fullgraph_dynamic_and_exports():
    """One opaque node: torch.compile(fullgraph=True, dynamic=True) with AOTAutograd (forward and
    backward) keeps one graph across query counts; torch.export captures the op."""
    calls = []

    def backend(gm, example_inputs):
        calls.append(1)
        from torch._dynamo.backends.common import aot_autograd
        return aot_autograd(fw_compiler=lambda g, _: g, bw_compiler=lambda g, _: g)(gm, example_inputs)

    def run(values, image_index, locations, weights, proj_w, proj_b):
        return deform_sample_project(values, image_index, locations, weights, proj_w, proj_b, backend="grid")

    compiled = torch.compile(run, fullgraph=True, dynamic=True, backend=backend)
    for q in (7, 9, 11):  # (not equal to another size: duck sizing would merge them)
        args = inputs(seed=q, q=q)
        targs = with_grad(args)
        out = compiled(*targs)
        torch.testing.assert_close(out, naive_project(*args), atol=1e-12, rtol=1e-10)
        out.sum().backward()
        assert targs[2].grad is not None and targs[0][0].grad is not None
    assert len(calls) == 1, f"{len(calls)} graphs for 3 query counts"

    class M(torch.nn.Module):
        def forward(self, v0, v1, image_index, locations, weights, proj_w, proj_b):
            return run([v0, v1], image_index, locations, weights, proj_w, proj_b)

    values, *rest = inputs(seed=4)
    ep = torch.export.export(M(), (*values, *rest))
    assert "mssf_blocks.deform_sample_project" in str(ep.graph)
    torch.testing.assert_close(ep.module()(*values, *rest), naive_project(values, *rest), atol=1e-12, rtol=1e-10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="a CUDA GPU (benchmarks/gpu_check.py runs this)")
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_triton_backend_on_cuda_matches_the_grid_backend(dtype):
    """The compiled kernels on a GPU: output and every gradient against the grid backend on the same
    device (float64 grid for the reference), no fallback warning."""
    dev = torch.device("cuda")
    args = inputs(seed=6, q=300, m=8, d=32, c=16, sizes=((40, 60), (20, 30), (10, 15), (5, 8)), p=4)
    rounded = [[v.to(dtype).to(F64) for v in args[0]], args[1], *(t.to(dtype).to(F64) for t in args[2:])]
    ref_args = with_grad([[v.to(dev) for v in rounded[0]], *(t.to(dev) for t in rounded[1:])])
    ref = torch.ops.mssf_blocks.deform_sample_project(*ref_args, "grid")
    grad = torch.randn(ref.shape, dtype=F64, generator=torch.Generator().manual_seed(8)).to(dev)
    ref.backward(grad)
    targs = with_grad([[v.to(dev, dtype) for v in args[0]], args[1].to(dev), *(t.to(dev, dtype) for t in args[2:])])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = deform_sample_project(*targs, backend="triton")
        out.backward(grad.to(dtype))
    rel = 1e-5 if dtype == torch.float32 else 3e-2  # (bf16: rounded outputs and gradients)
    for name, got, want in [("out", out, ref), *zip(["values"] * 4 + ["locations", "weights", "proj_weight", "proj_bias"],
                                                    [v.grad for v in targs[0]] + [t.grad for t in targs[2:]],
                                                    [v.grad for v in ref_args[0]] + [t.grad for t in ref_args[2:]])]:
        err = (got.double() - want.detach()).abs().max().item()
        assert err <= rel * want.abs().max().item() + 1e-6, (name, err)


def test_ms_deform_sample_project_goes_through_the_op(monkeypatch):
    # ms_deform_sample_project's "auto" (shared raw maps) is the op: the backend the op resolves serves it
    # (forced to the grid path here by the op's environment variable) and matches the float64 loops; a
    # backend the op refuses is refused there too.
    args = inputs(seed=3)
    monkeypatch.setenv(sampling_op.ENV_VAR, "grid")
    served = []
    grid_path = sampling_op._AUTOGRAD_BACKENDS["grid"]
    monkeypatch.setitem(sampling_op._AUTOGRAD_BACKENDS, "grid", lambda *a: served.append(1) or grid_path(*a))
    out = ms_deform_sample_project(*args, method="auto")
    assert served == [1]
    torch.testing.assert_close(out, naive_project(*args), atol=1e-10, rtol=1e-8)
    monkeypatch.setenv(sampling_op.ENV_VAR, "triton")
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    with pytest.raises(MSSFError, match="'triton' cannot serve these inputs"):
        ms_deform_sample_project(*args, method="auto")


def test_bilinear_sample_reads_the_op_backends_pixels():
    # bilinear_sample (SFF, QueryInit) does not fit the op's contract (one projection shared by the
    # levels, attention weights; SFF has a bias once and a separate weight slice per level), but its
    # "gather" method is the CPU backend's sampling (deform/touched) and equals the op with one point,
    # one head, weight 1 and an identity projection, and the float64 loops.
    g = torch.Generator().manual_seed(5)
    image = torch.randn(2, 3, 4, 5, generator=g, dtype=F64)
    uv = torch.rand(6, 1, 2, generator=g, dtype=F64) * 1.4 - 0.2  # some outside the image
    batch = torch.tensor([0, 1, 1, 0, 1, 0])
    eye = torch.eye(3, dtype=F64).view(1, 3, 3)
    via_op = deform_sample_project([image.unsqueeze(1)], batch, uv.view(6, 1, 1, 1, 2), torch.ones(6, 1, 1, 1, dtype=F64),
                                   eye, backend="touched")[:, 0]
    naive, _ = naive_ms_deform([image.unsqueeze(1)], batch, uv.view(6, 1, 1, 1, 2), torch.ones(6, 1, 1, 1, dtype=F64))
    torch.testing.assert_close(via_op, naive[:, 0], atol=1e-12, rtol=0)
    for method in ("gather", "grid"):
        torch.testing.assert_close(bilinear_sample(image, uv, batch, method=method)[:, 0], via_op, atol=1e-12, rtol=0)


@needs_op
@pytest.mark.parametrize("backend", ["touched", "grid"])
def test_level_gradient_skipped_when_only_the_projection_needs_one(monkeypatch, backend):
    """Frozen levels, trained projection (MSDFF on fixed image features): the op's backward recomputes its
    forward without the dense level gradient; every other gradient is the float64 reference's."""
    args = inputs(seed=6)
    values, image_index = args[0], args[1]
    loc, wt, pw, pb = (t.detach().clone().requires_grad_() for t in args[2:])
    recorded = []
    fn = sampling_op._OP_BACKENDS[backend]
    monkeypatch.setitem(sampling_op._OP_BACKENDS, backend,
                        lambda lv, *a: recorded.append([v.requires_grad for v in lv]) or fn(lv, *a))
    out = torch.ops.mssf_blocks.deform_sample_project(values, image_index, loc, wt, pw, pb, backend)
    grad = torch.randn(out.shape, dtype=F64, generator=torch.Generator().manual_seed(7))
    out.backward(grad)
    assert recorded[-1] == [False] * len(values)  # (the backward's recomputation)
    _, ref_loc, ref_wt, ref_pw, ref_pb = reference_grads(args, grad)
    for got, want in ((loc.grad, ref_loc), (wt.grad, ref_wt), (pw.grad, ref_pw), (pb.grad, ref_pb)):
        torch.testing.assert_close(got, want, atol=1e-10, rtol=1e-8)
    assert all(v.grad is None for v in values)
