"""Tests for ``mssf_blocks.samplers``: SFF, QueryInit, FusionInputs, and what SFF and MSDFF share (empty
batches, permutation and batch independence, bad input). MSDFF against its references: ``test_msdff.py``.

References (``fusion_references.py``) are written independently of the code under test: per-level
``F.grid_sample`` on images projected pixel by pixel, naive loops over voxels/cameras, hand-worked numbers.
"""

import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit, sample_at_projection
from mssf_blocks.geometry import VoxelCentroidProjector
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.testing import assert_close, gradcheck64

sys.path.insert(0, str(Path(__file__).parent))
from fusion_references import (  # noqa: E402
    D64, make_projection, randomize_msdff, ref_bn_eval, scene)


# Tiny tensors: with 2 OpenMP threads on a loaded 2-core machine, each train-mode batch_norm call
# spins for ~10-50 ms (measured), which makes gradcheck 100x slower. One thread is plenty here.
pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------------------------------------
# SFF
# ---------------------------------------------------------------------------------------------------
# SFF against its references on every device, its float64 gradcheck, state-dict round trip and compile
# smoke: the shared block checks, test_sff_tester.py.


def test_sff_pixel_hit_every_level():
    gen = torch.Generator().manual_seed(2)
    levels = [torch.randn(2, 1, 3, 8, 12, generator=gen, dtype=D64),
              torch.randn(2, 1, 5, 4, 6, generator=gen, dtype=D64)]
    sff = SFF([3, 5], 4, dtype=D64)
    for l, lvl in enumerate(levels):
        hl, wl = lvl.shape[-2:]
        cols = torch.tensor([0, 3, wl - 1])
        rows = torch.tensor([hl - 1, 1, 0])
        uv = torch.stack([(cols.to(D64) + 0.5) / wl, (rows.to(D64) + 0.5) / hl], -1)[:, None]
        bidx = torch.tensor([1, 0, 1])
        got = sff.sample(levels, make_projection(uv, torch.ones(3, 1, dtype=torch.bool), bidx))
        start = sum(x.shape[2] for x in levels[:l])
        want = lvl[bidx, 0, :, rows, cols]  # (3, C_l)
        assert_close(got[:, start:start + lvl.shape[2]], want)


def test_pixel_hit_through_projector():
    # lidar2img with depth 1, u = x, v = y: a point at x = 2 i + 0.5 lands on pixel centre i of the
    # stride-2 level ((u + 0.5) / W = (i + 0.5) / W_l), the centroid being the single point.
    gen = torch.Generator().manual_seed(3)
    img_h, img_w = 8, 16
    level = torch.randn(1, 6, img_h // 2, img_w // 2, generator=gen, dtype=D64)
    l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]], dtype=D64)
    i, j = 5, 2
    pts = torch.tensor([[2 * i + 0.5, 2 * j + 0.5, 0.5]], dtype=D64)
    vox = SparseVoxels(torch.zeros(1, 6, dtype=D64), torch.tensor([[0, 0, 2 * j, 2 * i]], dtype=torch.int32),
                       (1, img_h, img_w), 1, voxel_size=(1.0, 1.0, 1.0), point_range_min=(0.0, 0.0, 0.0))
    proj = VoxelCentroidProjector()(vox, pts, torch.zeros(1, dtype=torch.long), l2i, (img_h, img_w))
    assert_close(sample_at_projection(level, proj), level[0, :, j, i][None])


def test_invalid_points_give_zero_and_no_gradient():
    gen = torch.Generator().manual_seed(4)
    levels, uv, _, bidx = scene(gen)
    valid = torch.zeros(uv.shape[:2], dtype=torch.bool)  # uv inside the image, but every camera invalid
    levels = [l.requires_grad_(True) for l in levels]
    sff = SFF([3, 2], 4, dtype=D64).train()
    proj = make_projection(uv, valid, bidx)
    assert torch.equal(sff.sample(levels, proj), torch.zeros(7, 5, dtype=D64))
    out = sff(levels, proj)
    assert torch.equal(out, torch.zeros(7, 4, dtype=D64))
    (out.sum() + sff.sample(levels, proj).sum()).backward()
    for l in levels:
        assert l.grad is None or torch.count_nonzero(l.grad) == 0


def test_behind_camera_via_projector_is_zero():
    # depth = z: the voxel at z < 0 is behind the camera, the other one is in front but off-image.
    l2i = torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]], dtype=D64)
    coords = torch.tensor([[0, 0, 1, 1], [0, 3, 1, 50]], dtype=torch.int32)
    vox = SparseVoxels(torch.zeros(2, 2, dtype=D64), coords, (4, 4, 64), 1, voxel_size=(1.0, 1.0, 1.0), point_range_min=(0.0, 0.0, -2.0))
    proj = VoxelCentroidProjector()(vox, torch.zeros(0, 3, dtype=D64), torch.zeros(0, dtype=torch.long), l2i, (4, 4))
    assert not proj.valid.any()
    level = torch.randn(1, 2, 4, 4, dtype=D64, requires_grad=True)
    sff = SFF([2], 3, dtype=D64)
    out = sff([level], proj)
    assert torch.equal(sff.sample([level], proj), torch.zeros(2, 2, dtype=D64))
    assert torch.equal(out, torch.zeros(2, 3, dtype=D64))


@pytest.mark.parametrize("kind", ["sff", "msdff"])
def test_empty_and_batch_without_voxels(kind):
    gen = torch.Generator().manual_seed(5)
    levels = [torch.randn(2, 1, 4, 5, 6, generator=gen, dtype=D64, requires_grad=True),
              torch.randn(2, 1, 4, 3, 3, generator=gen, dtype=D64, requires_grad=True)]
    if kind == "sff":
        mod = SFF([4, 4], 8, dtype=D64)
    else:
        mod = MSDFF(4, 8, value_dim=6, num_heads=2, num_levels=2, num_points=2, dtype=D64)
    mod.train()

    def run(n, bidx):
        uv = torch.rand(n, 1, 2, generator=gen, dtype=D64)
        proj = make_projection(uv, torch.ones(n, 1, dtype=torch.bool), bidx)
        q = torch.randn(n, 8, dtype=D64, requires_grad=True)
        return (mod(levels, proj) if kind == "sff" else mod(q, levels, proj)), q

    out, q = run(0, torch.zeros(0, dtype=torch.long))
    assert out.shape == (0, 8)
    out.sum().backward()  # no error; nothing to propagate
    for l in levels:
        l.grad = None
    out, q = run(4, torch.zeros(4, dtype=torch.long))  # sample 1 has no voxels
    assert torch.isfinite(out).all()
    (out * torch.randn(out.shape, generator=gen, dtype=D64)).sum().backward()
    for l in levels:
        assert torch.count_nonzero(l.grad[1]) == 0
        assert torch.count_nonzero(l.grad[0]) > 0


@pytest.mark.parametrize("kind", ["sff", "msdff"])
def test_permutation_and_batch_independence(kind):
    gen = torch.Generator().manual_seed(6)
    levels, uv, valid, bidx = scene(gen, n=9, chans=(4, 4))
    if kind == "sff":
        mod = SFF([4, 4], 6, dtype=D64)
    else:
        mod = MSDFF(4, 6, value_dim=8, num_heads=2, num_levels=2, num_points=3, dtype=D64)
        randomize_msdff(mod, gen)
    mod.eval()
    query = torch.randn(9, 6, generator=gen, dtype=D64)

    def run(lv, q, u, va, b):
        proj = make_projection(u, va, b)
        return mod(lv, proj) if kind == "sff" else mod(q, lv, proj)

    out = run(levels, query, uv, valid, bidx)
    perm = torch.randperm(9, generator=gen)
    assert_close(run(levels, query[perm], uv[perm], valid[perm], bidx[perm]), out[perm])
    # Changing sample 1's images never changes a sample-0 voxel's output.
    other = [l.clone() for l in levels]
    for l in other:
        l[1] = torch.randn(l[1].shape, generator=gen, dtype=D64)
    out2 = run(other, query, uv, valid, bidx)
    s0 = bidx == 0
    assert s0.any() and (~s0).any()
    assert torch.equal(out2[s0], out[s0])
    assert not torch.allclose(out2[~s0 & valid.any(1)], out[~s0 & valid.any(1)])


# ---------------------------------------------------------------------------------------------------
# QueryInit
# ---------------------------------------------------------------------------------------------------
def test_query_init_hand_worked():
    qi = QueryInit(2, 1, 3, (0.0, -10.0, -2.0, 20.0, 10.0, 2.0), dtype=D64).eval()
    centers = torch.tensor([[0.0, -10.0, -2.0], [20.0, 10.0, 2.0], [5.0, 0.0, 1.0]], dtype=D64)
    p = torch.tensor([[0, 0, 0], [1, 1, 1], [0.25, 0.5, 0.75]], dtype=D64)
    assert_close(qi.normalized_centers(centers), p)
    f_vox = torch.randn(3, 2, dtype=D64)
    f_img = torch.randn(3, 1, dtype=D64)
    x = torch.cat([f_vox, f_img, p], 1)
    assert_close(qi(f_vox, f_img, centers), ref_bn_eval(x @ qi.linear.weight.T + qi.linear.bias, qi.norm))
    with pytest.raises(MSSFError, match="f_img0"):
        qi(f_vox, torch.zeros(3, 2, dtype=D64), centers)
    with pytest.raises(MSSFError, match="point_cloud_range"):
        QueryInit(2, 1, 3, (0, 0, 0, 1, 1))


# ---------------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------------
def test_bad_inputs_name_the_argument():
    l2i = torch.eye(3, 4).expand(2, 1, 3, 4)
    pts, pb = torch.zeros(1, 3), torch.zeros(1, dtype=torch.long)
    ok = [torch.zeros(2, 4, 6, 8), torch.zeros(2, 4, 3, 4)]
    FusionInputs(ok, l2i, (12, 16), pts, pb)
    with pytest.raises(MSSFError, match=r"image_features\[1\]"):
        FusionInputs([ok[0], torch.zeros(3, 4, 3, 4)], l2i, (12, 16), pts, pb)
    with pytest.raises(MSSFError, match=r"image_features\[0\]"):
        FusionInputs([torch.zeros(2, 3, 4, 6, 8)], l2i, (12, 16), pts, pb)  # V=3 vs lidar2img V=1
    with pytest.raises(MSSFError, match=r"image_features\[0\]"):
        FusionInputs([torch.zeros(4, 6, 8)], l2i, (12, 16), pts, pb)
    with pytest.raises(MSSFError, match="image_size"):
        FusionInputs(ok, l2i, (12,), pts, pb)

    sff = SFF([4, 4], 8)
    proj = make_projection(torch.rand(3, 1, 2), torch.ones(3, 1, dtype=torch.bool), torch.zeros(3, dtype=torch.long))
    with pytest.raises(MSSFError, match=r"image_features\[1\]"):
        sff([ok[0], torch.zeros(2, 5, 3, 4)], proj)
    with pytest.raises(MSSFError, match="image_features: expected 2 levels"):
        sff(ok[:1], proj)
    bad_uv = make_projection(torch.rand(3, 2), torch.ones(3, 1, dtype=torch.bool), torch.zeros(3, dtype=torch.long))
    with pytest.raises(MSSFError, match=r"projection\.uv"):
        sff(ok, bad_uv)
    with pytest.raises(MSSFError, match="in_channels"):
        SFF(4, 8)

    mod = MSDFF(4, 8, num_heads=2, num_levels=2, num_points=1)
    with pytest.raises(MSSFError, match="query"):
        mod(torch.zeros(3, 7), ok, proj)
    with pytest.raises(MSSFError, match=r"image_features\[0\]"):
        mod(torch.zeros(3, 8), [torch.zeros(2, 5, 6, 8), torch.zeros(2, 5, 3, 4)], proj)
    with pytest.raises(MSSFError, match="value_channels"):
        MSDFF([4, 8], 8, num_heads=2, num_levels=2)
    with pytest.raises(MSSFError, match="value_dim.*defaults to value_channels"):
        MSDFF(6, 8, num_heads=4)  # value_dim = value_channels = 6 heads cannot split into 4
    with pytest.raises(MSSFError, match="value_dim: expected a multiple of num_heads=4.*got 10"):
        MSDFF(4, 8, value_dim=10, num_heads=4)
    with pytest.raises(MSSFError, match="value_dim"):
        MSDFF(4, 8, value_dim=0, num_heads=4)
    MSDFF(4, 10, num_heads=4)  # embed_dim need not be a multiple of num_heads (the heads split value_dim)
    with pytest.raises(MSSFError, match="method"):
        MSDFF(8, 8, method="cuda")
    with pytest.raises(MSSFError, match="value_projection"):
        MSDFF(8, 8, value_projection="never")
