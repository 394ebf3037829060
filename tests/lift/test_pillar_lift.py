"""Tests of HeightEmbedding and PillarLift."""

from __future__ import annotations

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.lift import voxelize_points
from mssf_blocks.lift import HeightEmbedding, PillarLift
from mssf_blocks.testing import assert_close, gradcheck64


def scene(stride=1, seed=0):
    """Points in a 4 x 6 (y, x) grid of 0.5 m cells with 3 z cells, two samples."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(40, 4, generator=g, dtype=torch.float64) * torch.tensor([3.0, 2.0, 1.5, 1.0],
                                                                               dtype=torch.float64)
    batch = torch.randint(0, 2, (40,), generator=g)
    vox = voxelize_points(pts, batch, 2, (0.5, 0.5, 0.5), (0.0, 0.0, 0.0), (3.0, 2.0, 1.5))
    return vox


def test_height_embedding_zero_init_and_lookup():
    emb = HeightEmbedding(3, 4)
    assert emb.weight.shape == (3, 4) and float(emb.weight.detach().abs().sum()) == 0
    with torch.no_grad():
        emb.weight.copy_(torch.arange(12.0).reshape(3, 4))
    assert emb(torch.tensor([2, 0])).tolist() == [[8.0, 9, 10, 11], [0.0, 1, 2, 3]]
    with pytest.raises(MSSFError, match="z"):
        emb(torch.tensor([3]))
    with pytest.raises(MSSFError, match="z"):
        emb(torch.tensor([0.0]))
    with pytest.raises(MSSFError, match="num_z"):
        HeightEmbedding(0, 4)


@pytest.mark.parametrize("stride", [1, 2])
def test_pillar_lift_module_matches_loop_and_round_trip(stride):
    vox = scene()
    d, h, w = vox.spatial_shape
    lift = PillarLift(channels=3, num_z=d, stride=stride).double()
    with torch.no_grad():
        lift.height_embedding.weight.normal_()
    hb, wb = lift.bev_shape(vox)
    assert (hb, wb) == (-(-h // stride), -(-w // stride))
    bev = torch.randn(2, 3, hb, wb, dtype=torch.float64)
    out = lift(bev, vox)
    emb = lift.height_embedding.weight
    exp = torch.stack([bev[b, :, y // stride, x // stride] + emb[z] for b, z, y, x in vox.coords.tolist()])
    assert_close(out.features, exp)
    assert torch.equal(out.coords, vox.coords)
    back = lift.to_bev(out)
    exp_bev = torch.zeros_like(bev)
    for f, (b, z, y, x) in zip(exp, vox.coords.tolist()):
        exp_bev[b, :, y // stride, x // stride] += f
    assert_close(back, exp_bev)
    sf, sc = lift.to_bev_sparse(out)
    assert_close(sf, torch.stack([exp_bev[b, :, y, x] for b, y, x in sc.tolist()]))
    # Empty pillars stay exactly zero.
    occupied = torch.zeros(2, hb, wb, dtype=torch.bool)
    for b, z, y, x in vox.coords.tolist():
        occupied[b, y // stride, x // stride] = True
    assert bool((~occupied).any()) and float(back.detach().permute(0, 2, 3, 1)[~occupied].abs().sum()) == 0


def test_zero_height_embedding_is_plain_copy_and_no_embedding_option():
    vox = scene()
    bev = torch.randn(2, 3, 4, 6, dtype=torch.float64)
    a = PillarLift(3, 3).double()(bev, vox).features
    b = PillarLift(3, 3, use_height_embedding=False)(bev, vox).features
    assert_close(a, b)
    assert PillarLift(3, 3, use_height_embedding=False).height_embedding is None


# float64 gradcheck of the module and the state-dict round trip: the shared block checks,
# test_pillar_lift_tester.py.
def test_height_embedding_gradient_counts():
    vox = scene()
    lift = PillarLift(2, 3, stride=2).double()
    with torch.no_grad():
        lift.height_embedding.weight.normal_()

    bev = torch.randn(2, 2, 2, 3, dtype=torch.float64)
    # Gradient of the embedding: each voxel adds its z row once per channel.
    lift.zero_grad()
    lift(bev, vox).features.sum().backward()
    counts = torch.bincount(vox.coords[:, 1].long(), minlength=3).double()
    assert_close(lift.height_embedding.weight.grad, counts[:, None].expand(3, 2))


def test_bad_input():
    vox = scene()
    lift = PillarLift(3, 3, stride=2)
    with pytest.raises(MSSFError, match="bev"):
        lift(torch.zeros(2, 3, 4, 6), vox)  # stride-1 map given to a stride-2 lift
    with pytest.raises(MSSFError, match="bev"):
        lift(torch.zeros(1, 3, 2, 3), vox)
    with pytest.raises(MSSFError, match="num_z"):
        PillarLift(3, 4)(torch.zeros(2, 3, 4, 6), vox)
    with pytest.raises(MSSFError, match="voxels"):
        lift(torch.zeros(2, 3, 2, 3), vox.features)
    with pytest.raises(MSSFError, match="stride"):
        PillarLift(3, 3, stride=(1, 2, 3))
    with pytest.raises(MSSFError, match="channels"):
        PillarLift(0, 3)
    assert "stride=(2, 2)" in repr(lift)
