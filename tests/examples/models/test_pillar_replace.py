"""PointPillars' fusion write-back: fused voxels summed per pillar replace the pillars they occupy."""

import pytest
import torch

from mssf_blocks import SparseVoxels
from mssf_blocks.lift import PillarLift
from mssf_examples.models.backbones.pillars import replace_occupied_pillars


def _voxels(stride, seed=0, n=40, c=3, dtype=torch.float64, batch=2):
    g = torch.Generator().manual_seed(seed)
    sy, sx = stride
    h, w = 4 * sy, 5 * sx  # voxel grid x/y cells: a 4 x 5 BEV map at this stride
    coords = torch.stack([torch.randint(0, batch, (n,), generator=g), torch.randint(0, 3, (n,), generator=g),
                          torch.randint(0, h, (n,), generator=g), torch.randint(0, w, (n,), generator=g)], 1)
    coords = torch.cat([coords, coords[:5]]).int()  # duplicate voxels are summed like any others
    feats = torch.randn(coords.shape[0], c, generator=g, dtype=dtype)
    v = SparseVoxels(features=feats, coords=coords, spatial_shape=(3, h, w), batch_size=batch,
                     voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))
    bev = torch.randn(batch, c, 4, 5, generator=g, dtype=dtype)
    return v, bev


# one image: index_add along its pixels, several: index_put; NCHW and channels-last maps are written in
# their own layout, a transposed dense map (no (C, H * W) view) through an NCHW copy
@pytest.mark.parametrize("batch", [1, 2])
@pytest.mark.parametrize("layout", ["nchw", "channels_last", "transposed"])
@pytest.mark.parametrize("stride", [(1, 1), (2, 2), (2, 3)])
def test_replace_occupied_pillars_matches_loop(stride, layout, batch):
    v, bev = _voxels(stride, batch=batch)
    if layout == "channels_last":
        bev = bev.contiguous(memory_format=torch.channels_last)
    elif layout == "transposed":  # dense, W-major memory
        bev = bev.transpose(2, 3).contiguous().transpose(2, 3)
    got = replace_occupied_pillars(bev, v, stride)
    ref = bev.clone()
    seen = set()
    for f, (b, _, y, x) in zip(v.features, v.coords.tolist()):
        cell = (b, y // stride[0], x // stride[1])
        if cell not in seen:  # first voxel of the pillar: its sum starts from zero
            ref[b, :, cell[1], cell[2]] = 0.0
            seen.add(cell)
        ref[b, :, cell[1], cell[2]] += f
    assert torch.equal(got, ref)
    assert 0 < len(seen) < batch * 4 * 5  # (some pillars occupied, some kept)
    assert torch.equal(bev, _voxels(stride, batch=batch)[1])  # the input map is left as it was


@pytest.mark.parametrize("batch", [1, 2])
@pytest.mark.parametrize("stride", [(1, 1), (2, 3)])
def test_replace_occupied_pillars_equals_dense_where_with_gradients(stride, batch):
    """The formulation it replaced: two dense to_bev maps (sums, occupancy) and a torch.where."""
    v, bev = _voxels(stride, seed=1, batch=batch)
    lift = PillarLift(3, 3, stride=stride)
    feats = v.features.clone().requires_grad_(True)
    bev_a = bev.clone().requires_grad_(True)
    bev_b = bev.clone().requires_grad_(True)
    vv = v.replace(features=feats)
    occupied = lift.to_bev(v.replace(features=torch.ones(v.num_voxels, 1, dtype=bev.dtype))) > 0
    ref = torch.where(occupied, lift.to_bev(vv), bev_a)
    got = replace_occupied_pillars(bev_b, vv, stride)
    assert torch.equal(got, ref)
    grad = torch.randn_like(ref)
    g_ref = torch.autograd.grad(ref, [feats, bev_a], grad)
    g_got = torch.autograd.grad(got, [feats, bev_b], grad)
    for a, b in zip(g_got, g_ref):
        assert torch.equal(a, b)


def test_replace_occupied_pillars_promotes_dtypes():
    v, bev = _voxels((1, 1), dtype=torch.float32)
    got = replace_occupied_pillars(bev.to(torch.bfloat16), v, (1, 1))
    assert got.dtype == torch.float32
