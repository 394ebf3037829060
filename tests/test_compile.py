"""``torch.compile(fullgraph=True, dynamic=True)`` of every fusion module: no graph break (fullgraph raises
on one), one graph for every voxel count (dynamo's compile counter), outputs and gradients equal to eager.

Cheap backends keep CI short: ``"eager"`` runs dynamo's captured graph as is (what graph breaks and
recompiles are about), ``"aot_eager"`` also traces the backward with AOTAutograd (one module). Inductor
compile time and speed are measured by ``benchmarks/compile.py``, not here.
"""

import copy
import gc

import pytest
import torch

from mssf_blocks import (
    MSDFF,
    SFF,
    FusionBlock,
    FusionInputs,
    PillarLift,
    QueryInit,
    SemanticGuidedHead,
    SparseVoxels,
)
from mssf_blocks import torch_versions as _compat
from mssf_blocks.functional.deform import kept
from mssf_blocks.geometry import CentroidProjection

torch._dynamo = pytest.importorskip("torch._dynamo")
from torch._dynamo.testing import CompileCounterWithBackend  # noqa: E402

# fullgraph capture of the blocks (their input checks) needs a newer dynamo than the floor's (mssf_blocks.torch_versions)
_NO_COMPILE = _compat.missing("compile_dynamic")
pytestmark = [pytest.mark.usefixtures("one_thread"),
              pytest.mark.skipif(_NO_COMPILE is not None, reason=str(_NO_COMPILE))]

VOXEL_COUNTS = (9, 17, 30, 51, 80)
RANGE = (0.0, -4.0, -1.0, 8.0, 4.0, 1.0)
# float64 throughout: the comparison with eager then sees formulation errors, not the float32 rounding of
# near-zero gradients (e.g. a BatchNorm bias), so the tolerance can be tight
F64 = torch.float64
L2I = torch.tensor([[[0.0, -8.0, 0.0, 32.0], [0.0, 0.0, -8.0, 16.0], [1.0, 0.0, 0.0, 1.0]]], dtype=F64)  # (1, 3, 4)
FEATS = [torch.randn(1, 8, 24, 32, generator=torch.Generator().manual_seed(0), dtype=F64),
         torch.randn(1, 8, 12, 16, generator=torch.Generator().manual_seed(1), dtype=F64)]


def _scene(n, seed):
    """``n`` distinct voxels of a (4, 16, 16) grid, ``3 n`` points (some outside it), features that need grad."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(4 * 16 * 16, generator=g)[:n]
    coords = torch.stack([torch.zeros(n, dtype=torch.long), idx // 256, idx // 16 % 16, idx % 16], 1).int()
    feats = torch.randn(n, 16, generator=g, dtype=F64).requires_grad_()
    vox = SparseVoxels(feats, coords, (4, 16, 16), 1, voxel_size=(0.5, 0.5, 0.5), point_range_min=RANGE[:3])
    pts = torch.rand(3 * n, 3, generator=g, dtype=F64) * torch.tensor([8.5, 8.0, 2.0], dtype=F64) + torch.tensor(
        RANGE[:3], dtype=F64)
    uv = torch.rand(n, 1, 2, generator=g, dtype=F64) * 1.2 - 0.1  # a projection for the samplers alone
    valid = (uv >= 0).all(-1) & (uv <= 1).all(-1)
    proj = CentroidProjection(uv, valid.float(), valid, torch.zeros(n, 3), valid[:, 0], vox.batch_index)
    return vox, pts, torch.zeros(3 * n, dtype=torch.long), proj


def _fusion_run(m, vox, pts, pb, proj):
    return m(vox, FusionInputs(FEATS, L2I, (48, 64), pts, pb)).features  # SparseVoxels in, SparseVoxels out


def _sampler_run(m, vox, pts, pb, proj):
    return m(FEATS, proj) if isinstance(m, SFF) else m(vox.features, FEATS, proj)


def _head_run(m, vox, pts, pb, proj):
    out, scores, logits = m(vox, return_logits=True)
    return out.features + logits[:, None]


BEV = torch.randn(1, 16, 16, 16, generator=torch.Generator().manual_seed(2), dtype=F64)


def _lift_run(m, vox, pts, pb, proj):
    lifted = m(BEV + vox.features.sum() * 0, vox)  # (the BEV map's gradient depends on the voxels)
    return m.to_bev(lifted.replace(features=lifted.features * vox.features))


def _query_init_run(m, vox, pts, pb, proj):
    return m(vox.features, vox.features[:, :8] * 2, vox.voxel_centers(dtype=F64))


CASES = {
    "SFF": (lambda: SFF([8, 8], 16), _sampler_run),
    "MSDFF": (lambda: MSDFF(8, 16, num_heads=2, num_levels=2, num_points=2), _sampler_run),
    "QueryInit": (lambda: QueryInit(16, 8, 16, RANGE), _query_init_run),
    "FusionBlock-SFF": (lambda: FusionBlock(SFF([8, 8], 16)), _fusion_run),
    "FusionBlock-MSDFF": (lambda: FusionBlock(MSDFF(8, 16, num_heads=2, num_levels=2, num_points=2),
                                              query_init=QueryInit(16, 8, 16, RANGE)), _fusion_run),
    "SemanticGuidedHead": (lambda: SemanticGuidedHead(16, hidden=(8,)), _head_run),
    "PillarLift": (lambda: PillarLift(16, 4), _lift_run),
}


def _check_compiled(name, training, backend):
    build, run = CASES[name]
    torch.manual_seed(0)
    base = build().double().train(training)
    torch._dynamo.reset()
    counter = CompileCounterWithBackend(backend)
    compiled = torch.compile(run, fullgraph=True, dynamic=True, backend=counter)
    frames = []
    for n in VOXEL_COUNTS:
        vox, pts, pb, proj = _scene(n, seed=n)
        outs = []
        for fn in (compiled, run):
            mod = copy.deepcopy(base)  # the same parameters and running statistics for both
            out = fn(mod, vox, pts, pb, proj)
            weight = torch.linspace(-1, 1, out.numel(), dtype=F64).view_as(out)
            grads = torch.autograd.grad((out * weight).sum(), [vox.features] + list(mod.parameters()),
                                        allow_unused=True)
            stats = [b.clone() for b in mod.buffers()]
            outs.append((out, grads, stats))
        frames.append(counter.frame_count)
        (o1, g1, s1), (o0, g0, s0) = outs
        torch.testing.assert_close(o1, o0, atol=1e-10, rtol=1e-10)
        for a, e in zip(g1, g0):
            assert (a is None) == (e is None)
            if a is not None:
                torch.testing.assert_close(a, e, atol=1e-10, rtol=1e-10)
        for a, e in zip(s1, s0):
            torch.testing.assert_close(a, e, atol=1e-12, rtol=1e-12)
    # one compilation, at the first voxel count; none of the other four counts recompiles
    assert frames[0] >= 1 and frames == [frames[0]] * len(VOXEL_COUNTS), frames
    # the sampling graphs kept by compiled forwards (functional/deform/kept.py) were all taken or freed
    gc.collect()
    assert kept.waiting() == 0


@pytest.mark.parametrize("name", list(CASES))
def test_compile_fullgraph_dynamic_no_recompile(name):
    # training mode: batch statistics over the visible rows and running-statistics updates are the harder
    # case; eval graphs are checked by the export tests (tests/test_export.py)
    _check_compiled(name, True, "eager")


def test_compile_fusion_block_with_aot_autograd_backward():
    _check_compiled("FusionBlock-MSDFF", True, "aot_eager")
