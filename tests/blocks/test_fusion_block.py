"""Tests for ``mssf_blocks.blocks.FusionBlock`` with real spconv parts (CPU)."""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

spconv = pytest.importorskip("spconv.pytorch")

from mssf_blocks.blocks import FusionBlock, infer_downsample_stride  # noqa: E402
from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit  # noqa: E402
from mssf_blocks.geometry import VoxelCentroidProjector  # noqa: E402
from mssf_blocks.sparse_voxels import SparseVoxels  # noqa: E402
from mssf_blocks.testing import assert_close  # noqa: E402
from mssf_blocks.voxel_grid import VoxelGrid  # noqa: E402


VOXEL_SIZE = (0.5, 0.5, 0.5)
RANGE_MIN = (0.0, -4.0, -1.0)
SHAPE = (4, 16, 20)  # z 2 m, y 8 m, x 10 m
IMAGE = (48, 64)


# Tiny tensors on a shared 2-core machine: OpenMP spinning dominates otherwise (see test_fusion).
pytestmark = [pytest.mark.spconv, pytest.mark.usefixtures("one_thread")]


def make_scene(seed=0, b=2, c=8, v=2, image_channels=6, num_points=60, stride=(1, 1, 1), shape=SHAPE):
    """Random points, their voxels (at ``stride``), two forward-looking cameras, two image levels."""
    gen = torch.Generator().manual_seed(seed)
    lo = torch.tensor(RANGE_MIN)
    extent = torch.tensor([10.0, 8.0, 2.0])
    # x in [1, 10) m (in front of the cameras), y and z over the whole range
    pts = torch.rand(num_points, 3, generator=gen) * extent * torch.tensor([0.9, 1.0, 1.0])
    pts = pts + lo + torch.tensor([1.0, 0, 0])
    pb = torch.randint(0, b, (num_points,), generator=gen)
    cell = torch.tensor(VOXEL_SIZE) * torch.tensor(stride[::-1], dtype=torch.float32)
    idx = ((pts - lo) / cell).floor().long()
    coords = torch.unique(torch.cat([pb[:, None], idx[:, [2, 1, 0]]], 1), dim=0).int()
    feats = torch.randn(coords.shape[0], c, generator=gen)
    voxels = SparseVoxels(feats, coords, shape, b, voxel_size=VOXEL_SIZE, point_range_min=RANGE_MIN, stride=stride)
    # camera 0 looks along +x (u = 32 - 40 y / x, v = 24 - 40 z / x), camera 1 is shifted sideways.
    cam0 = torch.tensor([[32.0, -40, 0, 0], [24, 0, -40, 0], [1, 0, 0, 0]])
    cam1 = cam0.clone()
    cam1[0, 3] = 60.0
    l2i = torch.stack([cam0, cam1])[:v].expand(b, v, 3, 4).contiguous()
    levels = [torch.randn(b, v, image_channels, IMAGE[0] // s, IMAGE[1] // s, generator=gen) for s in (4, 8)]
    inputs = FusionInputs(levels, l2i, IMAGE, pts, pb)
    return voxels, inputs


class Doubler(nn.Module):
    """A stand-in residual part: doubles spconv features (makes the fusion position observable)."""

    def forward(self, t):
        return t.replace_feature(t.features * 2.0)


def stage(cin, cout):
    down = spconv.SparseSequential(
        spconv.SparseConv3d(cin, cout, 3, stride=2, padding=1, bias=False, indice_key="sp2"),
        nn.BatchNorm1d(cout), nn.ReLU(),
    )
    blocks = spconv.SparseSequential(spconv.SubMConv3d(cout, cout, 3, padding=1, bias=False, indice_key="subm2"))
    return down, blocks


def f_img_of(fusion, voxels, inputs):
    proj = VoxelCentroidProjector()(voxels, inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size)
    return fusion(list(inputs.image_features), proj), proj


def test_spconv_in_spconv_out_keeps_index_cache():
    voxels, inputs = make_scene()
    torch.manual_seed(0)
    down, blocks = stage(8, 16)
    block = FusionBlock(SFF([6, 6], 16), VoxelGrid.covering(VOXEL_SIZE, RANGE_MIN, SHAPE), downsample=down,
                        blocks=blocks).eval()
    x = spconv.SparseConvTensor(voxels.features, voxels.coords, list(SHAPE), 2)
    out = block(x, inputs)
    assert isinstance(out, spconv.SparseConvTensor)
    assert {"sp2", "subm2"} <= set(out.indice_dict)

    # Independent composition: downsample, then fuse at stride 2 (the stride changes the centres of
    # empty voxels, so a wrong stride changes f_img), then the residual part.
    d = down(spconv.SparseConvTensor(voxels.features, voxels.coords, list(SHAPE), 2))
    dv = SparseVoxels(d.features, d.indices, tuple(d.spatial_shape), 2, voxel_size=VOXEL_SIZE, point_range_min=RANGE_MIN, stride=(2, 2, 2))
    f_img, proj = f_img_of(block.fusion, dv, inputs)
    assert proj.valid.any() and not proj.valid.all()
    want = blocks(d.replace_feature(d.features + f_img)).features
    assert_close(out.features, want)
    assert torch.equal(out.indices, d.indices)

    # The cache is valid: a later submanifold conv reuses "subm2", the inverse conv of "sp2" restores
    # exactly the input voxel set.
    later = spconv.SubMConv3d(16, 16, 3, padding=1, indice_key="subm2")(out)
    assert torch.equal(later.indices, out.indices)
    inv = spconv.SparseInverseConv3d(16, 4, 3, indice_key="sp2")(out)
    assert list(inv.spatial_shape) == list(SHAPE)
    a = {tuple(r) for r in inv.indices.tolist()}
    assert a == {tuple(r) for r in voxels.coords.tolist()}


@pytest.mark.parametrize("position", ["before_residual", "after_residual"])
def test_sparse_voxels_in_out_with_stride(position):
    voxels, inputs = make_scene(seed=1, stride=(2, 2, 2), shape=(2, 8, 10))
    down, blocks = stage(8, 16)
    block = FusionBlock(MSDFF(6, 16, num_heads=2, num_levels=2, num_points=2), downsample=down, blocks=blocks, position=position)
    assert block.downsample_stride == (2, 2, 2)
    out = block(voxels, inputs)
    assert isinstance(out, SparseVoxels)
    assert out.stride == (4, 4, 4)
    assert out.spatial_shape == (1, 4, 5)
    assert out.features.shape[1] == 16 and torch.isfinite(out.features).all()
    assert {"sp2", "subm2"} <= set(out.to_spconv().indice_dict)  # cache travels with SparseVoxels
    # (No backward here: spconv 2.3's CPU backward needs CUDA streams; see test_gradients_reach_images.)


@pytest.mark.parametrize("value_dim", [pytest.param(None, id="paper_width"), pytest.param(8, id="narrow_width")])
def test_gradients_reach_images_and_parameters(value_dim):
    voxels, inputs = make_scene(seed=6, c=8)
    levels = [l.clone().requires_grad_(True) for l in inputs.image_features]
    inputs = FusionInputs(levels, inputs.lidar2img, IMAGE, inputs.points, inputs.points_batch)
    msdff = MSDFF(6, 8, value_dim, num_heads=2, num_levels=2, num_points=2)
    qi = QueryInit(8, 6, 8, (*RANGE_MIN, 10.0, 4.0, 1.0))
    with torch.no_grad():  # at Deformable-DETR init the query has no effect (zero offset/attention weights)
        msdff.sampling_offsets.weight.normal_(0.0, 0.1)
    f = voxels.features.clone().requires_grad_(True)
    out = FusionBlock(msdff, blocks=Doubler(), query_init=qi)(voxels.replace(features=f), inputs)
    (out.features * torch.randn(out.features.shape)).sum().backward()
    for t in [f, *levels, msdff.sampling_offsets.weight, msdff.value_proj.weight, qi.linear.weight]:
        assert t.grad is not None and torch.isfinite(t.grad).all() and torch.count_nonzero(t.grad) > 0


def test_anisotropic_downsample_stride():
    voxels, inputs = make_scene(seed=2)
    down = spconv.SparseConv3d(8, 8, 3, stride=(1, 2, 2), padding=1, bias=False, indice_key="a")
    block = FusionBlock(SFF([6, 6], 8), downsample=down).eval()
    assert block.downsample_stride == (1, 2, 2)
    out = block(voxels, inputs)
    assert out.stride == (1, 2, 2) and out.spatial_shape == (4, 8, 10)


def test_infer_downsample_stride():
    seq = spconv.SparseSequential(
        spconv.SubMConv3d(2, 2, 3, indice_key="s"), spconv.SparseConv3d(2, 2, 3, stride=2),
        nn.BatchNorm1d(2), spconv.SparseConv3d(2, 2, 3, stride=(2, 1, 1)),
    )
    assert infer_downsample_stride(seq) == (4, 2, 2)
    assert infer_downsample_stride(None) == (1, 1, 1)
    with pytest.raises(MSSFError, match="downsample_stride"):
        infer_downsample_stride(nn.Identity())
    with pytest.raises(MSSFError, match="downsample_stride"):
        infer_downsample_stride(spconv.SparseInverseConv3d(2, 2, 3, indice_key="x"))
    assert FusionBlock(SFF([6], 8), downsample=nn.Identity(), downsample_stride=(1, 1, 1)).downsample_stride == (1, 1, 1)


def test_position_order_is_observable():
    voxels, inputs = make_scene(seed=3, c=6)
    sff = SFF([6, 6], 6).eval()
    with torch.no_grad():
        sff.norm.running_mean.normal_()  # non-trivial f_img
    f = voxels.features
    g, proj = f_img_of(sff, voxels, inputs)
    seen = proj.valid.any(1)
    assert seen.any() and (~seen).any()
    before = FusionBlock(sff, blocks=Doubler(), position="before_residual")(voxels, inputs).features
    after = FusionBlock(sff, blocks=Doubler(), position="after_residual")(voxels, inputs).features
    assert_close(before, 2 * (f + g))
    assert_close(after, 2 * f + g)
    assert not torch.allclose(before[seen], after[seen])
    # A voxel no camera sees keeps its feature: f_fuse = f_vox + 0.
    fused = FusionBlock(sff)(voxels, inputs).features
    assert torch.equal(fused[~seen], f[~seen])


@pytest.mark.parametrize("value_dim", [pytest.param(None, id="paper_width"), pytest.param(8, id="narrow_width")])
def test_first_msdff_block_uses_query_init(value_dim):
    voxels, inputs = make_scene(seed=4, c=8, v=1, num_points=40)
    pcr = (*RANGE_MIN, 10.0, 4.0, 1.0)
    msdff = MSDFF(6, 8, value_dim, num_heads=2, num_levels=2, num_points=2).eval()
    qi = QueryInit(8, 6, 8, pcr).eval()
    block = FusionBlock(msdff, query_init=qi)
    captured = {}
    msdff.register_forward_hook(lambda mod, args, out: captured.update(query=args[0]))
    block(voxels, inputs)
    proj = VoxelCentroidProjector()(voxels, inputs.points, inputs.points_batch, inputs.lidar2img, IMAGE)
    # level-0 image feature by grid_sample, voxel centres by the formula (index + 0.5) * size + min.
    lvl0 = inputs.image_features[0][:, 0]
    f_img0 = torch.zeros(voxels.num_voxels, 6)
    for n in range(voxels.num_voxels):
        if proj.valid[n, 0]:
            grid = (2 * proj.uv[n, 0] - 1).view(1, 1, 1, 2)
            f_img0[n] = F.grid_sample(lvl0[voxels.batch_index[n]][None], grid, align_corners=False)[0, :, 0, 0]
    zyx = voxels.coords[:, 1:].float()
    centres = (zyx[:, [2, 1, 0]] + 0.5) * torch.tensor(VOXEL_SIZE) + torch.tensor(RANGE_MIN)
    assert_close(captured["query"], qi(voxels.features, f_img0, centres))
    # Without query_init the query is the voxel feature itself.
    FusionBlock(msdff)(voxels, inputs)
    assert torch.equal(captured["query"], voxels.features)


def test_bad_arguments():
    voxels, inputs = make_scene(seed=5)
    x = voxels.to_spconv()
    with pytest.raises(MSSFError, match="voxel_size"):
        FusionBlock(SFF([6, 6], 8))(x, inputs)
    with pytest.raises(MSSFError, match="channels"):
        FusionBlock(SFF([6, 6], 16))(voxels, inputs)
    with pytest.raises(MSSFError, match="query_init"):
        FusionBlock(SFF([6, 6], 8), query_init=QueryInit(8, 6, 8, (0, 0, 0, 1, 1, 1)))
    with pytest.raises(MSSFError, match="query_init"):
        FusionBlock(MSDFF(6, 8, num_heads=2, num_levels=2), query_init=QueryInit(8, 6, 16, (0, 0, 0, 1, 1, 1)))
    with pytest.raises(MSSFError, match="position"):
        FusionBlock(SFF([6, 6], 8), position="middle")
    with pytest.raises(MSSFError, match="fusion"):
        FusionBlock(nn.Linear(2, 2))
    with pytest.raises(MSSFError, match="inputs"):
        FusionBlock(SFF([6, 6], 8))(voxels, list(inputs.image_features))
    with pytest.raises(MSSFError, match="x"):
        FusionBlock(SFF([6, 6], 8))(voxels.features, inputs)
    with pytest.raises(MSSFError, match=r"image_features\[1\]"):
        FusionBlock(SFF([6, 4], 8))(voxels, inputs)


def test_extra_repr():
    block = FusionBlock(SFF([6, 6], 8), downsample=spconv.SparseConv3d(8, 8, 3, stride=2), position="after_residual")
    text = repr(block)
    assert "position='after_residual'" in text and "downsample_stride=(2, 2, 2)" in text
