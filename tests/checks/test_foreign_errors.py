"""Issue 42, "foreign errors": mistakes that ended in a traceback from spconv or torch (or in our error naming
the wrong argument) get our MSSFError, naming the argument to change and both figures, before spconv runs.

Every case asserts the exception type exactly (an spconv AssertionError or torch's ValueError is not an
MSSFError) and the message's key parts. Each failed on the code before this change (see the report of
the change: run against the previous ``src/``).
"""

from __future__ import annotations

import pytest
import torch
from torch import nn

from mssf_blocks import SparseVoxels, VoxelGrid
from mssf_blocks.blocks import FusionBlock
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit
from mssf_blocks.geometry import CentroidProjection
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.lift import PillarLift

spconv = pytest.importorskip("spconv.pytorch")

# (one thread: spconv's CPU float64 kernels are right only with one, and check_spconv_input refuses float64 otherwise)
pytestmark = pytest.mark.usefixtures("one_thread")

GRID = dict(voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))
#: the same grid as one object (a (4, 8, 8) tensor at stride 1), for FusionBlock
VOXEL_GRID = VoxelGrid.covering(GRID["voxel_size"], GRID["point_range_min"], (4, 8, 8))
# a pinhole camera looking down z: u = 10 x / z + 4 on an 8 x 8 image
L2I = torch.tensor([[[10.0, 0, 4, 0], [0, 10, 4, 0], [0, 0, 1, 0]]])


def indices(n=None):
    g = torch.Generator().manual_seed(0)
    zyx = torch.unique(torch.randint(0, 8, (60, 3), generator=g) % torch.tensor([4, 8, 8]), dim=0)
    idx = torch.cat([torch.zeros(len(zyx), 1, dtype=torch.long), zyx], 1).int()
    return idx if n is None else idx[:n]


def inputs(batch=1, channels=4, levels=None, l2i=None, points_to_sensor=None):
    pts = torch.rand(50, 3, generator=torch.Generator().manual_seed(1)) * 0.8
    levels = levels if levels is not None else [torch.randn(batch, channels, 8, 8)]
    l2i = L2I.expand(batch, 3, 4).clone() if l2i is None else l2i
    return FusionInputs(levels, l2i, (8, 8), pts, torch.zeros(50, dtype=torch.long), points_to_sensor)


def downsample(cin=4, cout=8):
    return spconv.SparseSequential(spconv.SparseConv3d(cin, cout, 3, stride=2, padding=1, bias=False),
                                   nn.BatchNorm1d(cout), nn.ReLU())


def residual(cin=8, cout=8):
    return spconv.SparseSequential(spconv.SubMConv3d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm1d(cout))


def block(fusion, ds=True, **kw):
    return FusionBlock(fusion, downsample=downsample() if ds else None, grid=VOXEL_GRID, **kw)


def sparse(features, idx=None, batch_size=1):
    idx = indices(features.shape[0]) if idx is None else idx
    return spconv.SparseConvTensor(features, idx, [4, 8, 8], batch_size)


def msdff(embed_dim=8, value_channels=4, **kw):
    return MSDFF(value_channels, embed_dim, num_heads=2, num_levels=1, num_points=1, **kw)


# ---------------------------------------------------------------------------------------------------
# an spconv tensor into a FusionBlock: the checks of SparseVoxels.to_spconv, and what the downsample takes
# ---------------------------------------------------------------------------------------------------
def _int64_indices():
    x = sparse(torch.randn(20, 4))
    x.indices = x.indices.long()  # (spconv's constructor refuses int64; a later assignment does not)
    return x


SPCONV_CASES = {
    "float64 features, float32 block": (lambda: sparse(torch.randn(20, 4, dtype=torch.float64)),
                                        r"^x\.features: expected dtype torch\.float32 \(the parameters of downsample's "
                                        r"first convolution \(SparseConv3d\)\), got torch\.float64"),
    "bfloat16 features": (lambda: sparse(torch.randn(20, 4).bfloat16()),
                          r"^x\.features: expected dtype torch\.float32 .*got torch\.bfloat16"),
    "zero voxels": (lambda: sparse(torch.randn(0, 4), indices()[:0]),
                    r"^x: expected at least one voxel for spconv, got 0"),
    "int64 indices": (_int64_indices, r"^x\.indices: expected dtype torch\.int32 .*got torch\.int64.*\.int\(\)"),
    "integer features": (lambda: sparse(torch.ones(20, 4, dtype=torch.long)),
                         r"^x\.features: expected a floating dtype .*got torch\.int64"),
    "channels not the downsample's": (lambda: sparse(torch.randn(20, 5)),
                                      r"^x\.features: expected 4 channels \(in_channels=4 of downsample's first "
                                      r"convolution \(SparseConv3d\)\), got 5"),
}


@pytest.mark.parametrize("case", sorted(SPCONV_CASES))
def test_spconv_tensor_into_a_fusion_block_gets_our_error(case):
    make, pattern = SPCONV_CASES[case]
    with pytest.raises(MSSFError, match=pattern):
        block(SFF([4], 8)).eval()(make(), inputs())


def test_spconv_tensor_without_downsample_gets_the_same_checks():
    blk = FusionBlock(SFF([4], 4), grid=VOXEL_GRID).eval()
    with pytest.raises(MSSFError, match=r"^x: expected at least one voxel for spconv, got 0"):
        blk(sparse(torch.randn(0, 4), indices()[:0]), inputs())
    with pytest.raises(MSSFError, match=r"^x\.indices: expected dtype torch\.int32"):
        blk(_int64_indices(), inputs())


def test_sparse_voxels_into_the_downsample_get_the_same_checks():
    v = SparseVoxels.from_spconv(sparse(torch.randn(20, 4, dtype=torch.float64)), **GRID)
    with pytest.raises(MSSFError, match=r"^x\.features: expected dtype torch\.float32 .*SparseConv3d.*got torch\.float64"):
        block(SFF([4], 8)).eval()(v, inputs())
    v = SparseVoxels.from_spconv(sparse(torch.randn(20, 6)), **GRID)
    with pytest.raises(MSSFError, match=r"^x\.features: expected 4 channels \(in_channels=4 .*got 6"):
        block(SFF([4], 8)).eval()(v, inputs())


@pytest.mark.parametrize("position,pattern", [
    ("before_residual", r"^f_fuse\.features: expected 6 channels \(in_channels=6 of blocks' first convolution "
                        r"\(SubMConv3d\)\), got 8"),
    ("after_residual", r"^downsample\(x\)\.features: expected 6 channels \(in_channels=6 .*got 8"),
])
def test_residual_blocks_of_another_width_are_named(position, pattern):
    blk = block(SFF([4], 8), blocks=residual(6), position=position).eval()
    with pytest.raises(MSSFError, match=pattern):
        blk(sparse(torch.randn(20, 4)), inputs())


def test_a_biased_spconv_convolution_in_eval_mode_on_the_cpu_is_named():
    # spconv adds the bias inside its inference kernel, which asserts on CPU tensors; in training it adds it after
    ds = spconv.SparseSequential(spconv.SparseConv3d(4, 8, 3, stride=2, padding=1), nn.BatchNorm1d(8))
    blk = FusionBlock(SFF([4], 8, norm_layer=None), downsample=ds, grid=VOXEL_GRID)
    with pytest.raises(MSSFError, match=r"^downsample\.0: expected no bias in eval mode on the CPU, got a SparseConv3d "
                                        r"with a bias.*bias=False"):
        blk.eval()(sparse(torch.randn(20, 4)), inputs())
    assert blk.train()(sparse(torch.randn(20, 4)), inputs()).features.shape[1] == 8


def test_a_tensor_batch_size_still_works():
    # mmdet3d's SparseEncoder hands spconv `coors[-1, 0] + 1`, a 0-d tensor: accepted (not read) as before
    x = spconv.SparseConvTensor(torch.randn(20, 4), indices(20), [4, 8, 8], torch.tensor(1))
    out = block(SFF([4], 8), blocks=residual()).eval()(x, inputs())
    assert out.features.shape[1] == 8


def test_example_backbone_checks_its_input_convolution():
    from mssf_blocks.integrations import _backbones

    net = _backbones.build("VoxelBackBone8x", 4, [0, -25.6, -3, 51.2, 25.6, 2], [0.8, 0.8, 0.125], num_fusion_blocks=0)
    coords = torch.tensor([[0, 1, 2, 3], [0, 2, 3, 4]], dtype=torch.int32)
    with pytest.raises(MSSFError, match=r"^voxels\.features: expected dtype torch\.float32 .*conv_input's first "
                                        r"convolution.*got torch\.float64"):
        _backbones.run_dense_layout(net, torch.randn(2, 4, dtype=torch.float64), coords, 1, None)
    with pytest.raises(MSSFError, match=r"^voxels\.features: expected 4 channels \(in_channels=4 .*got 5"):
        _backbones.run_dense_layout(net, torch.randn(2, 5), coords, 1, None)


# ---------------------------------------------------------------------------------------------------
# one row into a training-mode BatchNorm: our error on every path
# ---------------------------------------------------------------------------------------------------
def projection(n, visible):
    valid = torch.zeros(n, 1, dtype=torch.bool)
    valid[list(visible)] = True
    return CentroidProjection(uv=torch.full((n, 1, 2), 0.5), depth=torch.ones(n, 1), valid=valid,
                              centroid=torch.zeros(n, 3), has_points=torch.ones(n, dtype=torch.bool),
                              batch_index=torch.zeros(n, dtype=torch.long))


@pytest.mark.parametrize("method", ["auto", "reference", "fast", "grid"])
def test_msdff_with_one_seen_voxel_in_training_is_our_error(method):
    mod = msdff(method=method).train()
    with pytest.raises(MSSFError, match=r"^projection: exactly one of the 5 voxels is visible.*BatchNorm1d.*eval"):
        mod(torch.randn(5, 8), [torch.randn(1, 4, 8, 8)], projection(5, [2]))


def test_query_init_of_one_voxel_in_training_is_our_error():
    qi = QueryInit(8, 4, 8, (0, 0, 0, 1, 1, 1)).train()
    with pytest.raises(MSSFError, match=r"^f_vox: exactly one voxel \(N = 1\).*BatchNorm1d.*QueryInit"):
        qi(torch.randn(1, 8), torch.randn(1, 4), torch.rand(1, 3))
    blk = FusionBlock(msdff(), query_init=qi, grid=VOXEL_GRID).train()
    v = SparseVoxels(torch.randn(1, 8), torch.tensor([[0, 0, 2, 2]], dtype=torch.int32), (4, 8, 8), 1, **GRID)
    with pytest.raises(MSSFError, match=r"BatchNorm1d in training mode .*one row"):
        blk(v, inputs())


def test_semantic_head_refuses_one_row_only_with_a_training_batch_norm():
    one = SparseVoxels(torch.randn(1, 4), torch.tensor([[0, 0, 1, 1]], dtype=torch.int32), (4, 8, 8), 1, **GRID)
    with pytest.raises(MSSFError, match=r"^voxels: a single voxel.*BatchNorm1d in training mode"):
        SemanticGuidedHead(4, hidden=(8,)).train()(one)
    # LayerNorm normalises each row: one voxel is fine (it was refused as if it were a BatchNorm)
    out, scores = SemanticGuidedHead(4, hidden=(8,), norm_layer=nn.LayerNorm).train()(one)
    assert scores.shape == (1,)


# ---------------------------------------------------------------------------------------------------
# batch sizes: the argument that disagrees is named, with what it disagrees with
# ---------------------------------------------------------------------------------------------------
def test_lidar2img_of_another_batch_is_named():
    with pytest.raises(MSSFError, match=r"^lidar2img: expected batch size 2 \(as image_features\[0\] of shape "
                                        r"\(2, 4, 8, 8\)\), got lidar2img of shape \(1, 3, 4\) \(batch size 1\)"):
        inputs(batch=2, l2i=L2I)


def test_the_odd_one_out_is_named_by_majority():
    p2s = torch.eye(4).expand(2, 4, 4)
    with pytest.raises(MSSFError, match=r"^image_features\[0\]: expected batch size 2 \(as lidar2img .*"
                                        r"points_to_sensor .*\), got image_features\[0\] of shape \(1, 4, 8, 8\)"):
        inputs(batch=1, l2i=L2I.expand(2, 3, 4), points_to_sensor=p2s)
    with pytest.raises(MSSFError, match=r"^points_to_sensor: expected batch size 2 .*got points_to_sensor of shape "
                                        r"\(3, 4, 4\) \(batch size 3\)"):
        inputs(batch=2, points_to_sensor=torch.eye(4).expand(3, 4, 4))
    with pytest.raises(MSSFError, match=r"^image_features\[1\]: expected batch size 2 .*got image_features\[1\] of "
                                        r"shape \(3, 4, 4, 4\)"):
        inputs(batch=2, levels=[torch.randn(2, 4, 8, 8), torch.randn(3, 4, 4, 4)])


def test_a_folded_multi_camera_level_is_named_as_such_not_as_a_batch_mismatch():
    l2i = L2I[:, None].expand(2, 3, 3, 4)  # (B=2, V=3)
    with pytest.raises(MSSFError, match=r"^image_features\[0\]: a 4-d level \(B, C, H, W\) means one camera, but V=3.*"
                                        r"\(6, 4, 8, 8\); a \(B\*V, C, H, W\) level: image_features\[0\]\.view\(2, 3,"):
        inputs(batch=2, levels=[torch.randn(6, 4, 8, 8)], l2i=l2i)


def test_camera_inputs_of_another_batch_than_the_voxels_name_both():
    with pytest.raises(MSSFError, match=r"^image_features\[0\], lidar2img: expected batch size 2 \(x\.batch_size\), "
                                        r"got image_features\[0\] of shape \(1, 4, 8, 8\) \(batch size 1\), lidar2img"):
        block(SFF([4], 8)).eval()(sparse(torch.randn(20, 4), batch_size=2), inputs(batch=1))


def test_per_sample_image_sizes_say_what_to_pass():
    with pytest.raises(MSSFError, match=r"^image_size: expected \(H, W\), got \[\(8, 8\), \(8, 8\)\]: 2 per-sample "
                                        r"sizes; pass one \(H, W\)"):
        FusionInputs([torch.zeros(2, 4, 8, 8)], L2I.expand(2, 3, 4), [(8, 8), (8, 8)], torch.zeros(0, 3),
                     torch.zeros(0, dtype=torch.long))


def test_mmdet3d_encoder_names_the_short_per_sample_list():
    pytest.importorskip("mmengine")
    from mssf_blocks.integrations import mmdet3d_plugin

    enc = mmdet3d_plugin.MSSFSparseEncoder(4, [41, 64, 64], [0, -25.6, -3, 51.2, 25.6, 2], [0.8, 0.8, 0.125],
                                           image_channels=[4], msdff_heads=2, msdff_points=1)
    coors = torch.tensor([[0, 1, 2, 3], [1, 2, 3, 4]], dtype=torch.int32)
    meta = {"lidar2img": torch.eye(4).numpy(), "img_shape": (8, 8), "pad_shape": (8, 8), "batch_input_shape": (8, 8)}
    with pytest.raises(MSSFError, match=r"^points: expected number of samples 2 \(batch_size\), got points \(a list "
                                        r"of 1\)"):
        enc(torch.randn(2, 4), coors, 2, points=[torch.rand(3, 4)], img_features=[torch.randn(2, 4, 8, 8)],
            batch_input_metas=[meta, meta])


# ---------------------------------------------------------------------------------------------------
# channels: the constructor argument to change, with both numbers
# ---------------------------------------------------------------------------------------------------
def test_msdff_embed_dim_against_the_stage_channels():
    with pytest.raises(MSSFError, match=r"MSDFF embed_dim=16\), got 8 \(the downsample's output\); build the MSDFF "
                                        r"with embed_dim=8"):
        block(msdff(embed_dim=16)).eval()(sparse(torch.randn(20, 4)), inputs())


def test_sff_out_channels_against_the_voxels():
    v = SparseVoxels(torch.randn(3, 4), indices(3), (4, 8, 8), 1, **GRID)
    with pytest.raises(MSSFError, match=r"SFF out_channels=6\), got 4 \(x\.features\); build the SFF with out_channels=4"):
        FusionBlock(SFF([4], 6), grid=VOXEL_GRID).eval()(v, inputs())


@pytest.mark.parametrize("make,pattern", [
    (lambda: SFF([4, 6], 8), r"^image_features\[1\]: .*got shape \(1, 4, 4, 4\): 4 channels, but SFF in_channels\[1\]=6"),
    (lambda: MSDFF(6, 8, num_heads=2, num_levels=2, num_points=1),
     r"^image_features\[0\]: .*got shape \(1, 4, 8, 8\): 4 channels, but MSDFF value_channels=6; build it with "
     r"value_channels=4"),
])
def test_image_level_channels_name_the_sampler_argument(make, pattern):
    levels = [torch.randn(1, 4, 8, 8), torch.randn(1, 4, 4, 4)]
    mod = make().eval()
    with pytest.raises(MSSFError, match=pattern):
        if isinstance(mod, SFF):
            mod(levels, projection(3, [0, 1]))
        else:
            mod(torch.randn(3, 8), levels, projection(3, [0, 1]))


def test_standalone_widths_name_the_constructor_argument():
    with pytest.raises(MSSFError, match=r"^query: expected 8 channels \(MSDFF embed_dim=8\), got shape \(3, 4\)"):
        msdff().eval()(torch.randn(3, 4), [torch.randn(1, 4, 8, 8)], projection(3, [0, 1]))
    qi = QueryInit(8, 4, 8, (0, 0, 0, 1, 1, 1))
    with pytest.raises(MSSFError, match=r"^f_vox: expected 8 channels \(QueryInit voxel_channels=8\), got shape \(3, 6\)"):
        qi(torch.randn(3, 6), torch.randn(3, 4), torch.rand(3, 3))
    with pytest.raises(MSSFError, match=r"^f_img0: expected 4 channels \(QueryInit image_channels=4\), got shape \(3, 5\)"):
        qi(torch.randn(3, 8), torch.randn(3, 5), torch.rand(3, 3))
    v = SparseVoxels(torch.randn(3, 4), indices(3), (4, 8, 8), 1, **GRID)
    with pytest.raises(MSSFError, match=r"^voxels\.features: expected 6 channels \(SemanticGuidedHead in_channels=6\), "
                                        r"got shape \(3, 4\)"):
        SemanticGuidedHead(6, hidden=(8,))(v)
    with pytest.raises(MSSFError, match=r"^bev: expected 4 channels \(PillarLift channels=4\), got shape \(1, 5, 8, 8\)"):
        PillarLift(4, 4)(torch.zeros(1, 5, 8, 8), v)
    with pytest.raises(MSSFError, match=r"raw voxel features \(N, 3\) for raw_conv \(PillarLift raw_channels=3\), "
                                        r"got \(3, 4\)"):
        PillarLift(4, 4, raw_channels=3)(torch.zeros(1, 4, 8, 8), v)
