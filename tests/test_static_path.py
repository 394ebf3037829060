"""The static-shape path of the blocks (taken under graph capture, forced by ``static_path``) and the
compile-aware value checks.

References: the eager paths (independently tested against loops and float64 in tests/samplers/test_sff.py, test_msdff.py etc.),
and hand-built bad inputs whose eager errors are known.
"""

import copy
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from mssf_blocks import SparseVoxels, VoxelCentroidProjector
from mssf_blocks.checks.tensors import check_finite, check_index_range, is_tracing, value_check
from mssf_blocks.static_path import static_path, use_static_path
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional import bilinear_sample
from mssf_blocks.functional.geometry import voxel_centroids
from mssf_blocks.static_path import segment_slots
from mssf_blocks.samplers import MSDFF, SFF
from mssf_blocks.samplers import msdff as msdff_module
from mssf_blocks.functional.deform import bag as deform_bag
from mssf_blocks.functional.deform import grid as deform_grid
from mssf_blocks.geometry import CentroidProjection

pytestmark = pytest.mark.usefixtures("one_thread")


def _projection(n, b, v, seed=0, inside=0.8):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, v, 2, generator=g) * 1.2 - 0.1
    valid = torch.rand(n, v, generator=g) < inside
    uv = torch.where(valid[..., None], uv, torch.full_like(uv, float("nan")))  # invalid entries may be NaN
    bi = torch.randint(0, b, (n,), generator=g)
    return CentroidProjection(uv, valid.float(), valid, torch.zeros(n, 3), valid[:, 0], bi)


def _levels(b, v, c=6, seed=1):
    g = torch.Generator().manual_seed(seed)
    shape = (b,) if v == 1 else (b, v)
    return [torch.randn(*shape, c, 10, 14, generator=g, dtype=torch.float64).requires_grad_(),
            torch.randn(*shape, c, 5, 7, generator=g, dtype=torch.float64).requires_grad_()]


def _perturb(mod, seed=2):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in mod.parameters():
            p.add_(0.2 * torch.randn(p.shape, generator=g))
    return mod


@pytest.mark.parametrize("b,v", [(1, 1), (2, 1), (2, 3)])
@pytest.mark.parametrize("training", [False, True])
@pytest.mark.parametrize("kind", ["sff", "msdff", "msdff_raw_rows", "msdff_projected_levels", "msdff_onnx_form",
                                  "msdff_onnx_raw_levels", "msdff_onnx_mixed", "msdff_channels_last", "msdff_blocks"])
def test_static_path_equals_eager_forward_backward_and_running_stats(kind, training, b, v, monkeypatch):
    """MSDFF's static path (bag.sample_project_static) per level bags the raw channels and projects per head
    after ("msdff_raw_rows", forced; "msdff_channels_last": the same on channels-last levels, whose tables
    are free views) or projects every pixel first ("msdff_projected_levels", forced); "msdff": its own
    choice; "msdff_onnx_form" is what an ONNX export captures instead (grid.sample_project_onnx, its own choice per
    level), "msdff_onnx_raw_levels" its raw-level form forced (GridSample of the raw channels, projected after,
    the bias times a ones map's samples), "msdff_onnx_mixed" one level of each form (1 x 1 Conv + GridSample per
    head on the other); "msdff_blocks": the static path's queries bagged in blocks of 7 (its block size made
    small; the last query repeated to fill the last block), one raw level and one projected."""
    n = 40
    # float64: the comparison then sees formulation errors, not float32 rounding of near-zero gradients
    proj = _projection(n, b, v)
    proj = CentroidProjection(proj.uv.double(), proj.depth, proj.valid, proj.centroid, proj.has_points,
                              proj.batch_index)
    inside = ((proj.uv >= 0) & (proj.uv <= 1)).all(-1)
    # the cases hold both: projections outside the image, and voxels seen by no camera
    assert bool((proj.valid & ~inside).any()) and bool((~proj.valid.any(1)).any())
    feats = _levels(b, v)
    if kind == "msdff_channels_last":
        feats = [f.detach().flatten(0, -4).contiguous(memory_format=torch.channels_last).view(f.shape)
                 .requires_grad_() for f in feats]
        assert feats[0].stride(-3) == 1
    query = torch.randn(n, 16, requires_grad=True, dtype=torch.float64)
    base = SFF([6, 6], 16) if kind == "sff" else MSDFF(6, 16, num_heads=2, num_levels=2, num_points=3)
    _perturb(base.double()).train(training)
    if kind.startswith("msdff_onnx"):
        monkeypatch.setattr(msdff_module, "_exporting_onnx", lambda: True)
    if kind in ("msdff_onnx_raw_levels", "msdff_onnx_mixed"):
        # (the mixed case: the 10 x 14 level raw, the 5 x 7 level projected first)
        monkeypatch.setattr(deform_grid, "_raw_pays", lambda level, *a: kind.endswith("raw_levels") or level.shape[-1] == 14)
    if kind in ("msdff_raw_rows", "msdff_channels_last", "msdff_projected_levels"):
        monkeypatch.setattr(deform_bag, "_dense_pays", lambda *args: kind == "msdff_projected_levels")
    if kind == "msdff_blocks":
        monkeypatch.setattr(deform_bag, "_dense_pays", lambda level, *a: level.shape[-1] == 7)
        # 7 queries' (queries * M, C) float64 raw samples a block: M = 2, C = 6
        monkeypatch.setattr(deform_bag, "_STATIC_BLOCK_BYTES", 7 * 2 * 6 * 8)
        pairs = n * v  # (the static layout takes every (voxel, camera) pair)
        assert deform_bag.static_blocks(pairs, 2, 6, 8) == -(-pairs // 7) > 1
    results = []
    for static in (False, True):
        mod = copy.deepcopy(base)
        with static_path(static):
            assert use_static_path() is static
            if kind != "sff":
                want = ("grid_conv" if kind.startswith("msdff_onnx") else "static_bag") if static else "sample_op"
                assert mod._plan("cpu")[0] == want
            out = mod(feats, proj) if kind == "sff" else mod(query, feats, proj)
        inputs = feats + ([query] if kind != "sff" else [])
        weight = torch.linspace(-1, 1, out.numel()).view_as(out)
        grads = torch.autograd.grad((out * weight).sum(), inputs + list(mod.parameters()))
        results.append((out, grads, mod.norm.running_mean.clone(), mod.norm.running_var.clone()))
    (o0, g0, m0, v0), (o1, g1, m1, v1) = results
    torch.testing.assert_close(o1, o0, atol=1e-10, rtol=1e-10)
    for a, e in zip(g1, g0):
        torch.testing.assert_close(a, e, atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(m1, m0, atol=1e-12, rtol=1e-12)
    torch.testing.assert_close(v1, v0, atol=1e-12, rtol=1e-12)
    assert bool((o1[~proj.valid.any(1)] == 0).all())  # unseen voxels: exact zeros on both paths


def test_static_bilinear_sample_matches_hand_values():
    img = torch.arange(12.0, dtype=torch.float64).view(1, 1, 3, 4)
    # pixel centres (y, x) = (0, 0), (2, 3); the midpoint of (1, 1)-(1, 2); outside -> 0
    uv = torch.tensor([[[0.5 / 4, 0.5 / 3]], [[3.5 / 4, 2.5 / 3]], [[2.0 / 4, 1.5 / 3]], [[1.5, 0.5]]],
                      dtype=torch.float64)
    with static_path():
        out = bilinear_sample(img, uv, torch.zeros(4, dtype=torch.long)).flatten().tolist()
    assert out == [0.0, 11.0, 5.5, 0.0]


def test_static_centroids_equal_eager_including_duplicates_and_outside_points():
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(300, 3, generator=g) * torch.tensor([4.0, 4.0, 2.0]) - 0.5  # some outside the grid
    pb = torch.randint(0, 2, (300,), generator=g)
    coords = torch.cat([torch.randint(0, 2, (60, 1)), torch.randint(0, 2, (60, 1)), torch.randint(0, 4, (60, 2))], 1)
    coords = torch.cat([coords, coords[:5]]).int()  # duplicate rows get the same centroid
    args = (pts, pb, coords, (2, 4, 4), 2, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    c0, h0 = voxel_centroids(*args)
    with static_path():
        c1, h1 = voxel_centroids(*args)
    torch.testing.assert_close(c1, c0)
    assert torch.equal(h1, h0)


def test_segment_slots_groups_equal_keys():
    keys = torch.tensor([5, -1, 3, 5, 3, 9, -1])
    slots = segment_slots(keys)
    for i in range(len(keys)):
        for j in range(len(keys)):
            assert (slots[i] == slots[j]).item() == (keys[i] == keys[j]).item()
    assert int(slots.max()) < len(keys)


def test_value_checks_run_eagerly_and_are_skipped_under_compile():
    bad = torch.tensor([0, 7])
    with pytest.raises(MSSFError, match=r"idx: expected values in \[0, 3\)"):
        check_index_range(bad, "idx", 3, "n")
    with pytest.raises(MSSFError, match="finite"):
        check_finite(torch.tensor([float("nan")]), "x")
    assert not is_tracing()

    @value_check
    def check_positive(x, name):
        if bool((x <= 0).any()):
            raise MSSFError(f"{name}: expected positive values")
        return x

    def f(x, i):
        check_index_range(i, "idx", 3, "n")
        check_finite(x, "x")
        return check_positive(x, "x") * 2 + i.sum()

    compiled = torch.compile(f, fullgraph=True, backend="eager")  # fullgraph: a graph break would raise
    out = compiled(torch.tensor([float("nan"), -1.0]), bad)
    assert out[1].item() == 5.0  # the data checks were left out of the graph


_TRACE_SCRIPT = textwrap.dedent(
    """
    import io, sys, torch
    from torch import nn
    from mssf_blocks import torch_versions as _compat
    from mssf_blocks.functional import bilinear_sample
    from mssf_blocks.samplers import SFF, MSDFF
    from mssf_blocks.geometry import CentroidProjection

    torch.manual_seed(0)
    n = 20
    img = torch.randn(1, 4, 8, 8)
    uv = torch.rand(n, 1, 2)
    bi = torch.zeros(n, dtype=torch.long)
    f = torch.jit.trace(lambda a, b, c: bilinear_sample(a, b, c), (img, uv, bi))  # default method
    print("bilinear", (f(img, uv, bi) - bilinear_sample(img, uv, bi)).abs().max().item())

    class Wrap(nn.Module):
        def __init__(self, fusion):
            super().__init__()
            self.fusion = fusion
        def forward(self, q, l0, l1, uv, valid, bi):
            p = CentroidProjection(uv, valid.float(), valid, torch.zeros(uv.shape[0], 3), valid[:, 0], bi)
            if isinstance(self.fusion, SFF):
                return self.fusion([l0, l1], p)
            return self.fusion(q, [l0, l1], p)

    args = (torch.randn(n, 16), torch.randn(1, 4, 8, 8), torch.randn(1, 4, 4, 4), uv,
            torch.rand(n, 1) > 0.2, bi)
    for fusion in (SFF([4, 4], 16), MSDFF(4, 16, num_heads=2, num_levels=2, num_points=2)):
        w = Wrap(fusion).eval()
        t = torch.jit.trace(w, args)
        print(type(fusion).__name__, (t(*args) - w(*args)).abs().max().item())
        # the legacy exporter traces; before torch 2.5 (no dynamo= argument) it is the only one
        legacy = {"dynamo": False} if _compat.has("onnx_dynamo") else {}
        torch.onnx.export(w, args, io.BytesIO(), opset_version=17, **legacy)
        print("legacy onnx ok")
    """
)


def test_jit_trace_and_legacy_onnx_export_do_not_crash_the_interpreter():
    # Before the static path, tracing bilinear_sample's gather (index_fill_ with a bool scalar) aborted in
    # the tracer (an internal assert here, SIGSEGV on other builds): run it in a child process.
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in sys.path if p), OMP_NUM_THREADS="1")
    pytest.importorskip("onnx")
    res = subprocess.run([sys.executable, "-c", _TRACE_SCRIPT], capture_output=True, text=True, env=env,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    lines = [ln.split() for ln in res.stdout.splitlines()]
    diffs = {ln[0]: float(ln[1]) for ln in lines if len(ln) == 2 and ln[0] != "legacy"}
    assert set(diffs) == {"bilinear", "SFF", "MSDFF"}
    assert max(diffs.values()) < 1e-5
    assert res.stdout.count("legacy onnx ok") == 2


def test_projector_static_path_equals_eager():
    g = torch.Generator().manual_seed(4)
    pts = torch.rand(200, 3, generator=g) * 4.0
    pb = torch.randint(0, 2, (200,), generator=g)
    coords = torch.unique(torch.cat([pb[:, None], torch.zeros(200, 1, dtype=torch.long),
                                     (pts[:, [1, 0]] // 1.0).long()], 1), dim=0).int()
    vox = SparseVoxels(torch.zeros(coords.shape[0], 2), coords, (1, 4, 4), 2, voxel_size=(1.0, 1.0, 4.0), point_range_min=(0.0, 0.0, 0.0))
    l2i = torch.tensor([[0.0, -20.0, 0.0, 40.0], [0.0, 0.0, -20.0, 40.0], [1.0, 0.0, 0.0, 1.0]]).expand(2, 3, 4)
    p0 = VoxelCentroidProjector()(vox, pts, pb, l2i, (80, 80))
    with static_path():
        p1 = VoxelCentroidProjector()(vox, pts, pb, l2i, (80, 80))
    for name in ("uv", "valid", "centroid", "has_points"):
        torch.testing.assert_close(getattr(p1, name), getattr(p0, name))


def test_auto_plan_per_device_and_grid_method_equals_cpu_planner():
    from mssf_blocks.functional.plan_costs import bilinear_auto_method, msdff_auto_method

    # CUDA (and any non-CPU device) and graph capture: project first + grid_sample, no cost model
    assert msdff_auto_method("cuda", False) == "grid" and msdff_auto_method("cpu", True) == "grid"
    assert msdff_auto_method("cpu", False) == "touched"
    assert bilinear_auto_method("cuda", False) == "grid" and bilinear_auto_method("cpu", False) == "gather"
    proj = _projection(50, 2, 2)
    proj = CentroidProjection(proj.uv.double(), proj.depth, proj.valid, proj.centroid, proj.has_points,
                              proj.batch_index)
    feats = _levels(2, 2)
    query = torch.randn(50, 16, dtype=torch.float64)
    auto = _perturb(MSDFF(6, 16, num_heads=2, num_levels=2, num_points=3).double()).eval()
    grid = copy.deepcopy(auto)
    grid.method = "grid"  # the plan CUDA takes eagerly
    torch.testing.assert_close(grid(query, feats, proj), auto(query, feats, proj), atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize("v", [1, 2])
def test_static_msdff_bias_counts_only_the_in_image_weight_mass(v):
    # Voxels projected far outside the image (valid, but every corner of every point outside): in the
    # project-first formulation they read zero *projected* pixels, so value_proj.bias must not reach them;
    # voxels inside read it times their in-image bilinear mass. Both paths, float64, against each other
    # and against the bias-free property.
    g = torch.Generator().manual_seed(5)
    n = 24
    uv = torch.rand(n, v, 2, generator=g, dtype=torch.float64)
    far = torch.arange(n) % 3 == 0
    uv[far] = 40.0  # offsets of a few pixels cannot bring these back into the image
    valid = torch.ones(n, v, dtype=torch.bool)
    valid[1::6] = False  # and a few voxels seen by no camera
    bi = torch.zeros(n, dtype=torch.long)
    proj = CentroidProjection(uv, valid.double(), valid, torch.zeros(n, 3), valid[:, 0], bi)
    feats = [f.detach() for f in _levels(1, v)]
    query = torch.randn(n, 16, generator=g, dtype=torch.float64)
    mod = _perturb(MSDFF(6, 16, num_heads=2, num_levels=2, num_points=3, norm_layer=None).double()).eval()
    shifted = copy.deepcopy(mod)
    with torch.no_grad():
        shifted.value_proj.bias.add_(3.0)
    outs = {}
    for static in (False, True):
        with static_path(static), torch.no_grad():
            outs[static] = (mod(query, feats, proj), shifted(query, feats, proj))
    torch.testing.assert_close(outs[True][0], outs[False][0], atol=1e-10, rtol=1e-10)
    torch.testing.assert_close(outs[True][1], outs[False][1], atol=1e-10, rtol=1e-10)
    for static in (False, True):
        base, moved = outs[static]
        outside = far & valid.any(1)
        torch.testing.assert_close(moved[outside], base[outside], atol=1e-12, rtol=0)  # no bias outside
        inside = ~far & valid.any(1)
        assert bool(((moved[inside] - base[inside]).abs().amax(1) > 1e-3).all())  # the bias reaches the others
        assert bool((base[~valid.any(1)] == 0).all())  # unseen voxels: exact zeros


def test_static_msdff_cost_grows_with_the_voxels_not_the_pixels():
    # The static path's multiply-adds (FlopCounterMode counts the GEMMs / convolutions) do not grow with the
    # image size; project-first (method="grid") grows with the pixels. Independent: the count of the other
    # formulation on the same inputs.
    from torch.utils.flop_counter import FlopCounterMode

    def flops(mod, size):
        feats = [torch.randn(1, 8, size, size), torch.randn(1, 8, size // 2, size // 2)]
        proj = _projection(30, 1, 1)
        with static_path(), FlopCounterMode(display=False) as counter, torch.no_grad():
            mod(torch.randn(30, 16), feats, proj)
        return counter.get_total_flops()

    static = MSDFF(8, 16, num_heads=2, num_levels=2, num_points=2).eval()
    grid = copy.deepcopy(static)
    grid.method = "grid"
    # (levels of 32 x 32 pixels and more: the planner bags their raw rows; it projects only levels whose
    # every pixel costs less than the queries' raw corners, bag._dense_pays)
    assert flops(static, 64) == flops(static, 256) > 0
    assert flops(grid, 256) > 4 * flops(grid, 64) > 0
    with static_path():  # measured on the CPU only: other devices keep the grid plan (a cheap GEMM on a GPU)
        assert static._plan("cpu") == ("static_bag", True) and static._plan("cuda") == ("grid", True)
