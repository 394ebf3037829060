"""Precision rules of the image samplers (SFF, MSDFF, ``sample_at_projection``, FusionBlock).

The sampling runs in float32 (float64 for a float64 module), never in half precision, also under
``torch.autocast``: image levels in float16 / bfloat16 are read as float32, ``uv`` is converted to
the sampling dtype, and a float64 tensor into a float32 module is refused. References: the same
module run in float32 without autocast (exact equality where nothing is rounded, a bfloat16
tolerance where autocast rounds the output projection), and hand-placed sampling points on a noise
image where a location rounded to bfloat16 would read other pixels.
"""

import pytest
import torch

from mssf_blocks import torch_versions as _compat
from mssf_blocks.blocks import FusionBlock
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit, sample_at_projection
from mssf_blocks.geometry import CentroidProjection, VoxelCentroidProjector
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.sparse_voxels import SparseVoxels

pytestmark = pytest.mark.usefixtures("one_thread")

LOW = [torch.bfloat16, torch.float16]
# float16 CPU autocast needs a newer torch than the library's floor (mssf_blocks.torch_versions); skipped there
_NO_CPU_F16 = _compat.missing("cpu_float16_autocast")
AMP = [torch.bfloat16, pytest.param(torch.float16, marks=pytest.mark.skipif(_NO_CPU_F16 is not None,
                                                                            reason=str(_NO_CPU_F16)))]


def projection(uv, valid=None):
    n, v, _ = uv.shape
    return CentroidProjection(
        uv=uv, depth=torch.ones(n, v, dtype=uv.dtype),
        valid=torch.ones(n, v, dtype=torch.bool) if valid is None else valid,
        centroid=torch.zeros(n, 3, dtype=uv.dtype), has_points=torch.ones(n, dtype=torch.bool),
        batch_index=torch.zeros(n, dtype=torch.long),
    )


# MSDFF value widths: value_dim = value_channels (the paper's, the default) and = embed_dim (narrow).
VALUE_DIMS = [pytest.param(None, id="paper_width"), pytest.param(16, id="narrow_width")]


def setup(seed=0, n=40, c=8, e=16, width=1024, levels=2, value_dim=None):
    """A wide noise image (one pixel's neighbour is unrelated to it) and points near its right edge,
    where a bfloat16 coordinate (resolution 2^-8 near 1) is off by about 4 pixels."""
    g = torch.Generator().manual_seed(seed)
    feats = [torch.randn(1, c, 8 // 2**i, width // 2**i, generator=g) for i in range(levels)]
    uv = torch.stack([0.85 + 0.1 * torch.rand(n, generator=g), 0.2 + 0.6 * torch.rand(n, generator=g)], 1)
    query = torch.randn(n, e, generator=g)
    msdff = MSDFF(c, e, value_dim, num_heads=4, num_levels=levels, num_points=2).eval()
    with torch.no_grad():  # query-dependent offsets and weights, as after training
        msdff.sampling_offsets.weight.normal_(0, 0.5, generator=g)
        msdff.attention_weights.weight.normal_(0, 0.5, generator=g)
        msdff.norm.running_mean.normal_(0, 0.1, generator=g)
    sff = SFF([c] * levels, e).eval()
    return feats, projection(uv[:, None]), query, msdff, sff


def test_msdff_locations_and_weights_stay_float32_under_autocast():
    feats, proj, query, msdff, _ = setup()
    sizes = [tuple(f.shape[-2:]) for f in feats]
    loc, wt = msdff.sampling_locations_and_weights(query, proj.uv[:, 0], sizes)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loc_a, wt_a = msdff.sampling_locations_and_weights(query, proj.uv[:, 0], sizes)
        # a query that autocast produced in bfloat16 is read exactly (bfloat16 -> float32 is exact)
        q16 = query.bfloat16()
        loc_b, _ = msdff.sampling_locations_and_weights(q16, proj.uv[:, 0], sizes)
    assert loc_a.dtype == wt_a.dtype == torch.float32
    assert torch.equal(loc_a, loc) and torch.equal(wt_a, wt)
    assert torch.equal(loc_b, msdff.sampling_locations_and_weights(q16.float(), proj.uv[:, 0], sizes)[0])


@pytest.mark.parametrize("value_dim", VALUE_DIMS)
@pytest.mark.parametrize("amp_dtype", AMP)
def test_msdff_and_sff_under_autocast_match_float32(amp_dtype, value_dim):
    feats, proj, query, msdff, sff = setup(value_dim=value_dim)
    ref_m = msdff(query, feats, proj)
    ref_s = sff(feats, proj)
    with torch.autocast("cpu", dtype=amp_dtype):
        out_m = msdff(query, feats, proj)
        out_s = sff(feats, proj)
    # Only the output Linear runs in half precision: relative error of a few 2^-8 (bfloat16).
    # Locations rounded to bfloat16 would move the points by pixels on this noise image: O(1) errors.
    for out, ref in ((out_m, ref_m), (out_s, ref_s)):
        assert torch.isfinite(out).all()
        err = (out.float() - ref).abs().max().item()
        assert err <= 0.03 * ref.abs().max().item(), err


@pytest.mark.parametrize("value_dim", VALUE_DIMS)
@pytest.mark.parametrize("low", LOW)
def test_low_precision_levels_are_read_as_float32(low, value_dim):
    feats, proj, query, msdff, sff = setup(value_dim=value_dim)
    feats_low = [f.to(low) for f in feats]
    feats_up = [f.float() for f in feats_low]  # the same values in float32
    assert torch.equal(msdff(query, feats_low, proj), msdff(query, feats_up, proj))
    assert torch.equal(sff(feats_low, proj), sff(feats_up, proj))
    got = sample_at_projection(feats_low[0], proj)
    assert got.dtype == torch.float32 and torch.equal(got, sample_at_projection(feats_up[0], proj))
    # gradients flow back into the low-precision levels, in their dtype
    leaves = [f.clone().requires_grad_() for f in feats_low]
    msdff(query, leaves, proj).sum().backward()
    assert all(f.grad is not None and f.grad.dtype == low and torch.isfinite(f.grad.float()).all() for f in leaves)


def test_float64_module_accepts_float32_uv():
    feats, proj, query, msdff, sff = setup(n=12, width=64)
    msdff, sff = msdff.double(), sff.double()
    feats = [f.double() for f in feats]
    proj64 = projection(proj.uv.double())
    assert torch.equal(msdff(query.double(), feats, proj), msdff(query.double(), feats, proj64))
    assert torch.equal(sff(feats, proj), sff(feats, proj64))
    assert torch.equal(sample_at_projection(feats[0], proj), sample_at_projection(feats[0], proj64))


def test_float64_inputs_into_float32_module_are_refused():
    feats, proj, query, msdff, sff = setup(n=5, width=64)
    with pytest.raises(MSSFError, match=r"image_features\[0\]: expected dtype torch.float32 or lower.*float64"):
        msdff(query, [f.double() for f in feats], proj)
    with pytest.raises(MSSFError, match=r"query: expected dtype torch.float32 or lower.*float64"):
        msdff(query.double(), feats, proj)
    with pytest.raises(MSSFError, match=r"image_features\[0\]: expected dtype torch.float32 or lower.*float64"):
        sff([f.double() for f in feats], proj)


@pytest.mark.parametrize("value_dim", VALUE_DIMS)
def test_bfloat16_modules_sample_in_float32(value_dim):
    feats, proj, query, msdff, sff = setup(value_dim=value_dim)
    out32_m, out32_s = msdff(query, feats, proj), sff(feats, proj)
    m16, s16 = msdff.to(torch.bfloat16), sff.to(torch.bfloat16)
    out_m = m16(query.bfloat16(), [f.bfloat16() for f in feats], proj)
    out_s = s16([f.bfloat16() for f in feats], proj)
    assert out_m.dtype == out_s.dtype == torch.bfloat16
    # Parameters, features and the output Linear are rounded to bfloat16; the locations are not.
    for out, ref in ((out_m, out32_m), (out_s, out32_s)):
        err = (out.float() - ref).abs().max().item()
        assert err <= 0.06 * ref.abs().max().item(), err


def test_fusion_block_trains_under_autocast():
    g = torch.Generator().manual_seed(3)
    n, c = 60, 16
    coords = torch.stack([torch.zeros(n), torch.randint(0, 4, (n,), generator=g),
                          torch.randint(0, 20, (n,), generator=g), torch.randint(0, 20, (n,), generator=g)], 1).int()
    coords = torch.unique(coords, dim=0)
    n = coords.shape[0]
    # voxel grid 0.5 m, x forward 2-12 m; camera looking along +x
    vox = SparseVoxels(torch.randn(n, c, generator=g), coords, (4, 20, 20), 1, voxel_size=(0.5, 0.5, 0.5), point_range_min=(2.0, -5.0, -1.0))
    pts = vox.voxel_centers()
    l2i = torch.tensor([[[320.0, -400.0, 0.0, 0.0], [240.0, 0.0, -400.0, 0.0], [1.0, 0.0, 0.0, 0.0]]])
    feats = [torch.randn(1, 32, 480 // s, 640 // s, generator=g) for s in (4, 8)]
    inputs = FusionInputs(image_features=feats, lidar2img=l2i, image_size=(480, 640), points=pts,
                          points_batch=torch.zeros(n, dtype=torch.long))
    block = FusionBlock(MSDFF(32, c, num_heads=4, num_levels=2, num_points=2),
                        query_init=QueryInit(c, 32, c, (2.0, -5.0, -1.0, 12.0, 5.0, 1.0)))
    head = SemanticGuidedHead(c, hidden=(16,))
    params = list(block.parameters()) + list(head.parameters())

    def step(autocast: bool):
        for p in params:
            p.grad = None
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            fused = block(vox, inputs)
            weighted, scores = head(fused)
            loss = weighted.features.float().pow(2).mean() + scores.float().mean()
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in params]

    loss32, grads32 = step(False)
    loss16, grads16 = step(True)
    # bfloat16 rounding upstream of the sampling (query, output projection, head) changes the loss by
    # well under 5 %; every parameter gets a finite gradient, the sampling offsets a non-zero one.
    assert torch.isfinite(loss16) and abs(loss16.item() - loss32.item()) <= 0.05 * abs(loss32.item())
    assert all(torch.isfinite(a).all() for a in grads16)
    i = next(k for k, p in enumerate(params) if p is block.fusion.sampling_offsets.weight)
    assert grads16[i].abs().max() > 0 and grads32[i].abs().max() > 0


@pytest.mark.parametrize("low", LOW)
def test_projector_computes_half_precision_points_in_float32(low):
    g = torch.Generator().manual_seed(5)
    coords = torch.unique(torch.stack([torch.zeros(80), torch.randint(0, 4, (80,), generator=g),
                                       torch.randint(0, 40, (80,), generator=g),
                                       torch.randint(0, 40, (80,), generator=g)], 1).int(), dim=0)
    vox = SparseVoxels(torch.zeros(coords.shape[0], 2), coords, (4, 40, 40), 1, voxel_size=(0.5, 0.5, 0.5), point_range_min=(20.0, -10.0, -1.0))
    # many points per voxel at x = 20-40 m: a bfloat16 sum of 40 m coordinates is off by metres
    pts = vox.voxel_centers()[torch.randint(0, coords.shape[0], (2000,), generator=g)]
    pts = (pts + (torch.rand(2000, 3, generator=g) - 0.5) * 0.5).to(low)
    l2i = torch.tensor([[[320.0, -400.0, 0.0, 0.0], [240.0, 0.0, -400.0, 0.0], [1.0, 0.0, 0.0, 0.0]]])
    pb = torch.zeros(2000, dtype=torch.long)
    got = VoxelCentroidProjector()(vox, pts, pb, l2i, (480, 640))
    ref = VoxelCentroidProjector()(vox, pts.float(), pb, l2i, (480, 640))  # the same coordinates, float32
    assert got.uv.dtype == got.centroid.dtype == torch.float32
    assert torch.equal(got.uv, ref.uv) and torch.equal(got.centroid, ref.centroid)
