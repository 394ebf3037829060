"""The Triton kernels on CPU tensors under ``TRITON_INTERPRET=1``, against the float64 references.

Not collected by the main pytest run (the interpreter must be switched on before ``triton`` is first
imported, and other tests import it through ``torch.compile``): ``test_triton_kernels.py`` runs this
file in a fresh ``pytest`` process. The interpreter costs about 5-10 ms per (program x level x point)
step, so the shapes are small and the query block large (one program per head).
"""

from __future__ import annotations

import os
import sys

assert "triton" not in sys.modules, "triton_interpret_cases.py must run in its own process (TRITON_INTERPRET)"
os.environ["TRITON_INTERPRET"] = "1"

import pytest  # noqa: E402
import torch  # noqa: E402

from mssf_blocks.functional.deform.triton import kernels as tk  # noqa: E402
from mssf_blocks.functional.sampling import ms_deform_sample_reference  # noqa: E402

from sampling_references import border_locations, naive_ms_deform, random_inputs  # noqa: E402

F64 = torch.float64
BLOCK = 64  # one program per head for every case here


def flatten_levels(values):
    """``L`` levels ``(I, M, d, H, W)`` -> the kernels' ``(I, S, M, d)``, shapes, starts (independent code)."""
    shapes = torch.tensor([list(v.shape[-2:]) for v in values], dtype=torch.int32)
    starts, acc = [], 0
    for h, w in shapes.tolist():
        starts.append(acc)
        acc += h * w
    flat = torch.cat([v.flatten(3).permute(0, 3, 1, 2) for v in values], 1).contiguous()
    return flat, shapes, torch.tensor(starts, dtype=torch.int32)


def reference_with_grads(values, image_index, locations, weights, grad_out):
    """Float64 reference output and gradients (grid_sample formulation with autograd)."""
    vals = [v.detach().to(F64).requires_grad_() for v in values]
    loc = locations.detach().to(F64).requires_grad_()
    wt = weights.detach().to(F64).requires_grad_()
    out = ms_deform_sample_reference(vals, image_index, loc, wt)
    out.backward(grad_out.to(F64))
    return out.detach(), [v.grad for v in vals], loc.grad, wt.grad


SIZES = {1: ((5, 7),), 2: ((6, 8), (3, 4)), 5: ((9, 11), (5, 6), (3, 3), (2, 2), (1, 1))}


@pytest.mark.parametrize(
    "q,m,d,levels,p,num_images",
    [
        (1, 1, 32, 1, 2, 1),  # N = 1
        (37, 8, 32, 2, 2, 2),  # N not a multiple of the block, 8 heads, 2 images
        (5, 1, 64, 5, 1, 3),  # 5 levels, d = 64
        (70, 1, 32, 1, 2, 2),  # N > the block: two programs, the second partly masked
    ],
)
def test_forward_and_gradients_match_float64(q, m, d, levels, p, num_images):
    sizes = SIZES[levels]
    values, image_index, locations, weights = random_inputs(
        num_images=num_images, mv=m, m=m, d=d, sizes=sizes, q=q, p=p, seed=q + m + d, spread=0.3)
    grad_out = torch.randn(q, m, d, dtype=F64, generator=torch.Generator().manual_seed(1))
    ref, ref_gv, ref_gl, ref_gw = reference_with_grads(values, image_index, locations, weights, grad_out)
    flat, shapes, starts = flatten_levels([v.float() for v in values])
    loc32, wt32 = locations.float(), weights.float()
    out = tk.deform_sample_forward(flat, shapes, starts, image_index, loc32, wt32, block_q=BLOCK)
    torch.testing.assert_close(out.to(F64), ref, atol=2e-5, rtol=1e-5)
    gv, gl, gw = tk.deform_sample_backward(flat, shapes, starts, image_index, loc32, wt32, grad_out.float(), True,
                                           block_q=BLOCK)
    torch.testing.assert_close(gv.to(F64), flatten_levels(ref_gv)[0], atol=2e-5, rtol=1e-5)
    # locations: derivative of a piecewise-bilinear function, scaled by the map size
    torch.testing.assert_close(gl.to(F64), ref_gl, atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(gw.to(F64), ref_gw, atol=2e-5, rtol=1e-5)


def test_border_and_outside_samples_match_naive_loops():
    """Pixel centres, pixel borders, image edges and outside (zero padding, no clamping), shared values (M = 1)."""
    sizes = ((4, 5), (2, 3))
    q, m, p, d = 9, 1, 4, 32
    values, image_index, _, weights = random_inputs(num_images=2, mv=1, m=m, d=d, sizes=sizes, q=q, p=p, seed=5)
    locations = border_locations(sizes, q, m, p, F64)
    ref, _ = naive_ms_deform(values, image_index, locations, weights)
    flat, shapes, starts = flatten_levels([v.float() for v in values])
    out = tk.deform_sample_forward(flat, shapes, starts, image_index, locations.float(), weights.float(), block_q=BLOCK)
    torch.testing.assert_close(out.to(F64), ref, atol=2e-5, rtol=1e-5)
    # far outside (|u| of 1e6) reads exact zeros
    far = torch.full_like(locations, 1e6).float()
    zero = tk.deform_sample_forward(flat, shapes, starts, image_index, far, weights.float(), block_q=BLOCK)
    assert torch.equal(zero, torch.zeros_like(zero))


def test_strided_locations_and_skipped_value_gradient():
    """MSDFF's locations are a (Q, M, L, P, 2) view of (Q, L, 2, M, P) memory; no value gradient asked."""
    q, m, levels, p, d = 6, 8, 2, 2, 32
    values, image_index, locations, weights = random_inputs(num_images=1, mv=m, m=m, d=d, sizes=SIZES[2], q=q,
                                                            p=p, seed=7)
    strided = locations.permute(0, 2, 4, 1, 3).contiguous().permute(0, 3, 1, 4, 2)
    assert not strided.is_contiguous() and torch.equal(strided, locations)
    grad_out = torch.randn(q, m, d, dtype=F64, generator=torch.Generator().manual_seed(2))
    ref, _, ref_gl, ref_gw = reference_with_grads(values, image_index, locations, weights, grad_out)
    flat, shapes, starts = flatten_levels([v.float() for v in values])
    out = tk.deform_sample_forward(flat, shapes, starts, image_index, strided.float(), weights.float(), block_q=BLOCK)
    torch.testing.assert_close(out.to(F64), ref, atol=2e-5, rtol=1e-5)
    gv, gl, gw = tk.deform_sample_backward(flat, shapes, starts, image_index, strided.float(), weights.float(),
                                           grad_out.float(), False, block_q=BLOCK)
    assert gv is None
    torch.testing.assert_close(gl.to(F64), ref_gl, atol=2e-4, rtol=1e-4)
    torch.testing.assert_close(gw.to(F64), ref_gw, atol=2e-5, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_inputs_accumulate_in_float32(dtype):
    """bf16 / fp16 values, locations and weights: the result is the float64 reference of the rounded
    inputs to within one output rounding (the accumulation runs in float32)."""
    q, m, levels, p, d = 5, 1, 2, 4, 32
    values, image_index, locations, weights = random_inputs(num_images=1, mv=m, m=m, d=d, sizes=SIZES[2], q=q,
                                                            p=p, seed=11)
    values = [v.to(dtype) for v in values]
    locations, weights = locations.to(dtype), weights.to(dtype)
    grad_out = torch.randn(q, m, d, generator=torch.Generator().manual_seed(3)).to(dtype)
    ref, ref_gv, ref_gl, ref_gw = reference_with_grads(values, image_index, locations, weights, grad_out)
    flat, shapes, starts = flatten_levels(values)
    out = tk.deform_sample_forward(flat, shapes, starts, image_index, locations, weights, block_q=BLOCK)
    assert out.dtype == dtype
    eps = torch.finfo(dtype).eps
    scale = ref.abs().max().item()
    torch.testing.assert_close(out.to(F64), ref, atol=2 * eps * scale, rtol=0)
    gv, gl, gw = tk.deform_sample_backward(flat, shapes, starts, image_index, locations, weights, grad_out, True,
                                           block_q=BLOCK)
    assert gv.dtype == gl.dtype == gw.dtype == dtype
    for got, want in ((gv, flatten_levels(ref_gv)[0]), (gl, ref_gl), (gw, ref_gw)):
        torch.testing.assert_close(got.to(F64), want, atol=2 * eps * want.abs().max().item(), rtol=0)


# ---------------------------------------------------------------------------------------------------
# the op's "triton" backend and MSDFF(method="triton")
# ---------------------------------------------------------------------------------------------------
def test_op_triton_backend_matches_float64_with_every_gradient():
    """Projection inside the op: gradients of the raw levels, locations, weights, proj weight and bias."""
    from mssf_blocks.functional.deform.op import deform_sample_project

    q, m, d, c, p = 9, 2, 32, 5, 2
    values, image_index, locations, weights = random_inputs(num_images=2, mv=1, m=m, d=c, sizes=SIZES[2], q=q, p=p,
                                                            seed=21)
    g = torch.Generator().manual_seed(22)
    proj_w, proj_b = torch.randn(m, d, c, generator=g, dtype=F64), torch.randn(m, d, generator=g, dtype=F64)
    grad_out = torch.randn(q, m, d, generator=g, dtype=F64)
    # float64 reference: sample the raw channels, project per head, bias times the in-image mass
    ref_in = [t.clone().requires_grad_() for t in (*values, locations, weights, proj_w, proj_b)]
    sampled, mass = ms_deform_sample_reference(ref_in[:2], image_index, ref_in[2], ref_in[3], return_mass=True)
    ref = torch.einsum("qmc,mdc->qmd", sampled, ref_in[4]) + mass[..., None] * ref_in[5]
    ref.backward(grad_out)
    got_in = [t.detach().float().requires_grad_() for t in ref_in]
    out = deform_sample_project(got_in[:2], image_index, *got_in[2:], backend="triton")
    torch.testing.assert_close(out.to(F64), ref.detach(), atol=5e-5, rtol=1e-5)
    out.backward(grad_out.float())
    for name, got, want in zip(("values[0]", "values[1]", "locations", "weights", "proj_weight", "proj_bias"),
                               got_in, ref_in):
        torch.testing.assert_close(got.grad.to(F64), want.grad, atol=5e-4, rtol=1e-4, msg=name)


def test_msdff_triton_matches_the_float64_module_reference():
    """MSDFF(method="triton") on two cameras with invalid pairs (every pair a query, invalid ones masked)."""
    from fusion_references import randomize_msdff, reference_msdff, scene
    from mssf_blocks.samplers import MSDFF

    gen = torch.Generator().manual_seed(5)
    levels, uv, valid, batch_index = scene(gen, b=2, v=2, n=6, chans=(4, 4))
    mod = MSDFF(4, 6, value_dim=8, num_heads=2, num_levels=2, num_points=2, method="triton").double()
    randomize_msdff(mod, gen)
    mod.eval()
    query = torch.randn(6, 6, generator=gen, dtype=F64)
    ref, _, _ = reference_msdff(mod, query, levels, uv, valid, batch_index)
    from fusion_references import make_projection
    mod32 = mod.float()
    out = mod32(query.float(), [lvl.float() for lvl in levels], make_projection(uv.float(), valid, batch_index))
    torch.testing.assert_close(out.to(F64), ref.detach(), atol=1e-4, rtol=1e-4)
    assert out[0].abs().max() == 0  # seen by no camera: exact zeros


def test_gpu_check_sampling_stage_runs_the_kernels_and_matches_the_grid_path():
    """benchmarks/_sampling_stage.py's Triton code path (toy sizes), as the GPU run will take it."""
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from _sampling_stage import sampling_benchmark

    rows = sampling_benchmark(torch.device("cpu"), smoke=True, repeats=1)
    assert [r["dtype"] for r in rows] == ["float32", "bfloat16"]
    assert rows[0]["triton_max_abs_diff"] < 1e-5 and rows[1]["triton_max_abs_diff"] < 5e-2
    assert all(r["triton_fwd_bwd_ms"] > 0 for r in rows)
