import pytest
import torch
import torch.nn.functional as F

pytest.importorskip("spconv")
import spconv.pytorch as spconv  # noqa: E402

from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_blocks.samplers import FusionInputs  # noqa: E402
from mssf_blocks.testing import assert_close  # noqa: E402
from mssf_examples.models.backbones import (  # noqa: E402
    CenterPointBackbone,
    PointPillarsBackbone,
    SECONDBackbone,
    SparseBasicBlock,
    VoxelNeXtBackbone,
    merge_sparse_bev,
    merge_sparse_bev_dense_reference,
)
from mssf_examples.models.voxelize import DynamicVoxelizer, VoxelGrid  # noqa: E402

GRID = VoxelGrid(voxel_size=(0.4, 0.4, 0.125), point_cloud_range=(0.0, -6.4, -3.0, 12.8, 6.4, 2.0))
PILLARS = VoxelGrid(voxel_size=(0.4, 0.4, 5.0), point_cloud_range=(0.0, -6.4, -3.0, 12.8, 6.4, 2.0))
# spconv's multi-threaded CPU kernels are not bit-deterministic between calls (differences of
# ~1e-5 relative); comparisons of two forward passes below need one thread.
pytestmark = pytest.mark.usefixtures("one_thread")


FUSION = dict(image_channels=[8, 8, 8, 8], msdff_heads=2, msdff_points=2, seg_hidden=(8,))


def _scene(seed=0, p=200):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(p, 5, generator=g)
    pts[:, 0] = pts[:, 0] * 12.0 + 0.4
    pts[:, 1] = pts[:, 1] * 12.0 - 6.0
    pts[:, 2] = pts[:, 2] * 4.0 - 2.5
    pb = torch.randint(0, 2, (p,), generator=g)
    feats = [torch.randn(2, 1, 8, 8 // s, 16 // s, generator=g) for s in (1, 2, 4, 8)]
    # a camera at the origin looking along +x (x_cam = -y, y_cam = -z, depth = x), f = 20 px
    l2i = torch.zeros(2, 1, 3, 4)
    l2i[:, :, 0, 1], l2i[:, :, 1, 2], l2i[:, :, 2, 0] = -20.0, -20.0, 1.0
    l2i[:, :, 0, 0], l2i[:, :, 1, 0] = 32.0, 16.0  # principal point (32, 16)
    return pts, pb, FusionInputs(feats, l2i, (32, 64), pts[:, :3], pb)


def test_merge_sparse_bev_equals_dense_scatter():
    g = torch.Generator().manual_seed(0)
    tensors = []
    for k, (h, w) in zip((1, 2, 4), ((16, 16), (8, 8), (4, 4))):
        n = 40
        coords = torch.stack([torch.randint(0, 2, (n,), generator=g), torch.randint(0, 3, (n,), generator=g),
                              torch.randint(0, h, (n,), generator=g), torch.randint(0, w, (n,), generator=g)], 1)
        coords = torch.unique(coords, dim=0).int()  # equal (b, y) x with different z stay: they must be summed
        tensors.append((torch.randn(coords.shape[0], 3, generator=g, dtype=torch.float64), coords))
    feats, coords = merge_sparse_bev(tensors, [1, 2, 4], 2, (16, 16))
    ref = merge_sparse_bev_dense_reference(tensors, [1, 2, 4], 2, (16, 16))
    dense = torch.zeros_like(ref)
    b, y, x = coords.long().unbind(1)
    dense[b, :, y, x] = feats
    assert_close(dense, ref)
    assert coords.shape[0] == torch.unique(coords, dim=0).shape[0]  # one row per (b, y, x)
    occupied = torch.zeros(2, 16, 16, dtype=torch.bool)
    for (_, c), k in zip(tensors, (1, 2, 4)):
        occupied[c[:, 0].long(), c[:, 2].long() * k, c[:, 3].long() * k] = True
    assert int(occupied.sum()) == coords.shape[0]
    with pytest.raises(MSSFError, match="BEV shape"):
        merge_sparse_bev(tensors, [1, 4, 4], 2, (16, 16))


def test_sparse_basic_block_matches_dense_conv_reference():
    torch.manual_seed(0)
    # float32: spconv 2.3.8's CPU float64 kernels are unreliable (wrong results on repeated calls)
    blk = SparseBasicBlock(3, "k").eval()
    for bn in (blk.bn1, blk.bn2):
        bn.running_mean.uniform_(-0.2, 0.2)
        bn.running_var.uniform_(0.5, 1.5)
    coords = torch.unique(torch.randint(0, 5, (30, 3)), dim=0)
    coords = torch.cat([torch.zeros(coords.shape[0], 1, dtype=torch.long), coords], 1).int()
    feats = torch.randn(coords.shape[0], 3)
    out = blk(spconv.SparseConvTensor(feats, coords, [5, 5, 5], 1))
    dense = torch.zeros(1, 3, 5, 5, 5)
    z, y, x = coords[:, 1].long(), coords[:, 2].long(), coords[:, 3].long()
    dense[0, :, z, y, x] = feats.T
    mask = torch.zeros(1, 1, 5, 5, 5)
    mask[0, 0, z, y, x] = 1

    def conv(t, w):  # spconv weight (out, kz, ky, kx, in) -> torch (out, in, kz, ky, kx)
        return F.conv3d(t, w.permute(0, 4, 1, 2, 3), padding=1) * mask

    def bn(t, m):
        sh = (1, -1, 1, 1, 1)
        return ((t - m.running_mean.view(sh)) / torch.sqrt(m.running_var.view(sh) + m.eps) * m.weight.view(sh)
                + m.bias.view(sh)) * mask

    h = torch.relu(bn(conv(dense, blk.conv1.weight), blk.bn1))
    h = torch.relu(bn(conv(h, blk.conv2.weight), blk.bn2) + dense)
    assert torch.equal(out.indices, coords)
    torch.testing.assert_close(out.features, h[0, :, z, y, x].T, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize(
    "cls, channels, strides",
    [
        (SECONDBackbone, (4, 4, 8, 8, 8), [(1, 1, 1), (2, 2, 2), (4, 4, 4), (8, 8, 8)]),
        (CenterPointBackbone, (4, 4, 8, 8, 16), [(1, 1, 1), (2, 2, 2), (4, 4, 4), (8, 8, 8)]),
        (VoxelNeXtBackbone, (8, 8, 8, 16, 16, 16, 16), [(2**i,) * 3 for i in range(6)]),
    ],
)
def test_sparse_backbone_layout_radar_only(cls, channels, strides):
    pts, pb, _ = _scene()
    vox = DynamicVoxelizer(GRID.point_cloud_range, GRID.voxel_size)(pts, pb, 2)
    bb = cls(5, GRID, channels=channels, out_channels=16).eval()
    out = bb(vox)
    assert [s.stride for s in out.stages] == strides
    assert [s.num_channels for s in out.stages] == list(channels[1:])
    # every voxel of a stage lies on the grid of that stride (centres inside the range)
    for s in out.stages:
        c = s.voxel_centers()
        assert (c[:, 0] > 0).all() and (c[:, 1] > -6.4).all() and (c[:, 1] < 6.4).all()
    if cls is VoxelNeXtBackbone:
        f, c = out.sparse_bev
        assert f.shape[1] == 16 and c.shape[1] == 3 and out.bev is None
    else:
        # SECOND layout with 41 z cells: 41 -> 21 -> 11 -> 5 -> conv_out -> 2, so C_bev = 2 * 16
        assert out.bev.shape == (2, 32, 4, 4) and bb.bev_channels == 32
    assert out.seg_logits is None


@pytest.mark.parametrize("cls, channels", [(SECONDBackbone, (4, 4, 8, 8, 8)), (VoxelNeXtBackbone, (8, 8, 8, 16, 16, 16, 16))])
@pytest.mark.parametrize("fusion, position", [("msdff", "before_residual"), ("sff", "after_residual")])
def test_fusion_backbone_uses_own_sample_images_only(cls, channels, fusion, position):
    torch.manual_seed(0)
    pts, pb, fi = _scene()
    vox = DynamicVoxelizer(GRID.point_cloud_range, GRID.voxel_size)(pts, pb, 2)
    bb = cls(5, GRID, channels=channels, out_channels=16, num_fusion_blocks=2, fusion=fusion,
             fusion_position=position, **FUSION).eval()
    out = bb(vox, fi)
    assert out.seg_logits.shape == (out.seg_voxels.num_voxels,) and out.seg_voxels.stride == (2, 2, 2)
    # changing sample 1's image changes sample 1's output, never sample 0's
    feats2 = [f.clone() for f in fi.image_features]
    for f in feats2:
        f[1] = torch.randn_like(f[1])
    out2 = bb(vox, FusionInputs(feats2, fi.lidar2img, fi.image_size, fi.points, pb))
    last, last2 = out.stages[-1], out2.stages[-1]
    s0 = last.batch_index == 0
    assert_close(last2.features[s0], last.features[s0])
    assert not torch.allclose(last2.features[~s0], last.features[~s0])


def test_fusion_backbone_gradient_reaches_image_and_radar_only_ignores_it():
    pts, pb, fi = _scene()
    vox = DynamicVoxelizer(GRID.point_cloud_range, GRID.voxel_size)(pts, pb, 2)
    feats = [f.clone().requires_grad_(True) for f in fi.image_features]
    fi = FusionInputs(feats, fi.lidar2img, fi.image_size, fi.points, pb)
    bb = CenterPointBackbone(5, GRID, channels=(4, 4, 8, 8, 16), out_channels=8, num_fusion_blocks=1, **FUSION)
    bb(vox, fi).bev.square().sum().backward()
    assert all(f.grad is not None and f.grad.abs().sum() > 0 for f in feats)
    radar = CenterPointBackbone(5, GRID, channels=(4, 4, 8, 8, 16), out_channels=8).eval()
    assert_close(radar(vox, fi).bev, radar(vox).bev)


@pytest.mark.parametrize("n, position", [(0, "before_residual"), (2, "before_residual"), (1, "after_residual")])
def test_pointpillars_backbone(n, position):
    torch.manual_seed(0)
    pts, pb, fi = _scene()
    bb = PointPillarsBackbone(5, PILLARS, lift_z_size=0.5, pfn_channels=8, layer_nums=(1, 1, 1), num_filters=(8, 16, 16),
                              num_upsample_filters=(8, 8, 8), num_fusion_blocks=n, fusion_position=position, **FUSION)
    out = bb(pts, pb, 2, fi)
    assert out.bev.shape == (2, 24, 16, 16) and bb.bev_shape == (16, 16)
    assert len(out.stages) == n
    if n:
        # fused voxels of block i sit at the BEV map's x/y resolution: stride (1, 2^(i+1), 2^(i+1))
        assert [s.stride for s in out.stages] == [(1, 2 ** (i + 1), 2 ** (i + 1)) for i in range(n)]
        assert out.seg_logits.shape == (out.stages[-1].num_voxels,)


def test_bad_settings():
    with pytest.raises(MSSFError, match="num_fusion_blocks"):
        SECONDBackbone(5, GRID, num_fusion_blocks=5, **FUSION)
    with pytest.raises(MSSFError, match="fusion"):
        SECONDBackbone(5, GRID, num_fusion_blocks=1, fusion="concat", **FUSION)
    with pytest.raises(MSSFError, match="image_channels"):
        SECONDBackbone(5, GRID, num_fusion_blocks=1)
    with pytest.raises(MSSFError, match="z extent"):
        SECONDBackbone(5, VoxelGrid(voxel_size=(0.5, 0.5, 0.25), point_cloud_range=(0, 0, 0, 4, 4, 1)))
    with pytest.raises(MSSFError, match="fusion_inputs"):
        pts, pb, _ = _scene()
        vox = DynamicVoxelizer(GRID.point_cloud_range, GRID.voxel_size)(pts, pb, 2)
        SECONDBackbone(5, GRID, channels=(4, 4, 8, 8, 8), num_fusion_blocks=1, **FUSION)(vox)



@pytest.mark.parametrize("s", [1, 2, 3, 8])
def test_pointpillars_coarsen_equals_naive_set(s):
    """_coarsen = the sorted set of (b, z, y // s, x // s) rows, with the ceil-divided shape."""
    from mssf_blocks import SparseVoxels
    from mssf_examples.models.backbones import PointPillarsBackbone

    g = torch.Generator().manual_seed(s)
    d, h, w, b = 3, 21, 17, 2
    n = 60
    coords = torch.stack([torch.randint(0, b, (n,), generator=g), torch.randint(0, d, (n,), generator=g),
                          torch.randint(0, h, (n,), generator=g), torch.randint(0, w, (n,), generator=g)], 1).int()
    coords = torch.unique(coords, dim=0)
    v = SparseVoxels(features=torch.zeros(coords.shape[0], 1), coords=coords, spatial_shape=(d, h, w), batch_size=b,
                     voxel_size=(0.2, 0.2, 0.5), point_range_min=(0.0, -2.0, -1.0))
    out = PointPillarsBackbone._coarsen(v, s)
    expect = sorted({(bb, z, y // s, x // s) for bb, z, y, x in coords.tolist()})
    assert out.coords.tolist() == [list(r) for r in expect]
    assert tuple(out.spatial_shape) == (d, -(-h // s), -(-w // s)) and tuple(out.stride) == (1, s, s)
    assert out.coords.dtype == coords.dtype and out.batch_size == b
