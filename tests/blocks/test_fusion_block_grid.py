"""FusionBlock on one VoxelGrid (issue 43): the stride of an spconv input read from its shape, the query
built by the block, the head's centroids handed back, and the old argument forms refused or kept."""

import dataclasses
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # (test_fusion_block's scene helpers)

spconv = pytest.importorskip("spconv.pytorch")

from mssf_blocks import FusionBlock, FusionBlockOutput, MSDFF, QueryInit, SemanticGuidedHead, SFF, VoxelGrid  # noqa: E402
from mssf_blocks import VoxelCentroidProjector, voxel_foreground_labels  # noqa: E402
from mssf_blocks.errors import MSSFError  # noqa: E402
from test_fusion_block import RANGE_MIN, SHAPE, VOXEL_SIZE, make_scene, stage  # noqa: E402

pytestmark = [pytest.mark.spconv, pytest.mark.usefixtures("one_thread")]

GRID = VoxelGrid.covering(VOXEL_SIZE, RANGE_MIN, SHAPE)


def test_query_init_true_is_the_explicit_query_init():
    voxels, inputs = make_scene(c=8)
    torch.manual_seed(0)
    down, blocks = stage(8, 16)
    built = FusionBlock(MSDFF(6, 16, num_heads=2, num_levels=2, num_points=2), GRID, downsample=down,
                        blocks=blocks, query_init=True).eval()
    assert isinstance(built.query_init, QueryInit)
    assert (built.query_init.voxel_channels, built.query_init.image_channels, built.query_init.out_channels) == (16, 6, 16)
    assert built.query_init.point_cloud_range == GRID.point_cloud_range
    explicit = FusionBlock(MSDFF(6, 16, num_heads=2, num_levels=2, num_points=2), downsample=down, blocks=blocks,
                           query_init=QueryInit(16, 6, 16, RANGE_MIN + GRID.point_range_max)).eval()
    explicit.load_state_dict(built.state_dict())
    x = spconv.SparseConvTensor(voxels.features, voxels.coords, list(SHAPE), 2)
    with torch.no_grad():
        torch.testing.assert_close(built(x, inputs).features, explicit(voxels, inputs).features, rtol=0, atol=0)


def test_the_stride_of_an_spconv_input_is_read_from_its_shape():
    voxels, inputs = make_scene(c=8)
    torch.manual_seed(0)
    down, blocks = stage(8, 16)
    block = FusionBlock(SFF([6, 6], 16), GRID, downsample=down, blocks=blocks).eval()
    x = spconv.SparseConvTensor(voxels.features, voxels.coords, list(SHAPE), 2)
    with torch.no_grad():
        mid = block.downsample(x)
        out = block(x, inputs)
    assert tuple(mid.spatial_shape) == (2, 8, 10) and GRID.stride_of(mid.spatial_shape) == (2, 2, 2)
    # the same block on the SparseVoxels of the same tensor (stride stated) gives the same features
    with torch.no_grad():
        torch.testing.assert_close(out.features, block(voxels, inputs).features, rtol=0, atol=0)


def test_the_head_hands_back_the_centroids_its_labels_need():
    voxels, inputs = make_scene(c=8)
    torch.manual_seed(0)
    down, blocks = stage(8, 16)
    for head_position in ("after_fusion", "after_residual"):
        block = FusionBlock(SFF([6, 6], 16), GRID, downsample=down, blocks=blocks,
                            semantic_head=SemanticGuidedHead(16, hidden=(8,)), head_position=head_position).eval()
        with torch.no_grad():
            res = block(voxels, inputs, return_logits=True)
        assert isinstance(res, FusionBlockOutput)
        out, head_voxels, logits = res  # unpacks as before
        assert logits.shape == (head_voxels.num_voxels,) and res.voxels is out
        # the independent way: project the voxels the head read a second time
        again = VoxelCentroidProjector()(head_voxels, inputs.points, inputs.points_batch, inputs.lidar2img,
                                         inputs.image_size)
        torch.testing.assert_close(res.centroids, again.centroid, rtol=0, atol=0)
        assert torch.equal(res.has_points, again.has_points) and torch.equal(res.batch_index, again.batch_index)
        boxes = [torch.tensor([[5.0, 0.0, 0.0, 4.0, 4.0, 2.0, 0.3]]), torch.zeros(0, 7)]
        labels, _ = voxel_foreground_labels(res.centroids, res.batch_index, boxes)
        want, _ = voxel_foreground_labels(again.centroid, again.batch_index, boxes)
        assert torch.equal(labels, want) and 0 < int((labels == 1).sum()) < labels.numel()


def test_the_head_centroids_when_the_head_reads_other_voxels():
    # residual blocks that are not submanifold change the voxel set: the centroids are computed for it
    voxels, inputs = make_scene(c=8)
    torch.manual_seed(0)
    grow = spconv.SparseSequential(spconv.SparseConv3d(8, 8, 3, stride=1, padding=1, bias=False))
    block = FusionBlock(SFF([6, 6], 8), GRID, blocks=grow, semantic_head=SemanticGuidedHead(8, hidden=(4,)),
                        head_position="after_residual").eval()
    with torch.no_grad():
        res = block(voxels, inputs, return_logits=True)
    assert res.head_voxels.num_voxels > voxels.num_voxels  # dilated
    again = VoxelCentroidProjector()(res.head_voxels, inputs.points, inputs.points_batch, inputs.lidar2img,
                                     inputs.image_size)
    torch.testing.assert_close(res.centroids, again.centroid, rtol=0, atol=0)
    # half-precision points (autocast inputs): the centroids of the new voxels in float32, as the projector's
    half = dataclasses.replace(inputs, points=inputs.points.half())
    with torch.no_grad():
        res = block(voxels, half, return_logits=True)
    again = VoxelCentroidProjector()(res.head_voxels, half.points, half.points_batch, half.lidar2img, half.image_size)
    assert res.centroids.dtype == torch.float32
    torch.testing.assert_close(res.centroids, again.centroid, rtol=0, atol=0)


def test_misuses_of_the_grid_are_refused_by_name():
    voxels, inputs = make_scene(c=8)
    down, blocks = stage(8, 16)
    with pytest.raises(MSSFError, match=r"grid: expected a VoxelGrid or None, got SparseSequential \(the second "
                                        r"argument is the grid now: pass downsample= by keyword\)"):
        FusionBlock(SFF([6, 6], 16), down, blocks)
    with pytest.raises(MSSFError, match=r"query_init: True builds a QueryInit from the block's grid"):
        FusionBlock(MSDFF(6, 16, num_heads=2, num_levels=2, num_points=2), query_init=True)
    with pytest.raises(MSSFError, match=r"query_init: only an MSDFF fusion takes a query; got query_init=True with SFF"):
        FusionBlock(SFF([6, 6], 16), GRID, query_init=True)
    x = spconv.SparseConvTensor(voxels.features, voxels.coords, list(SHAPE), 2)
    with pytest.raises(MSSFError, match=r"x: an spconv SparseConvTensor carries no metric grid; construct FusionBlock "
                                        r"with grid=VoxelGrid"):
        FusionBlock(SFF([6, 6], 16), downsample=down, blocks=blocks)(x, inputs)
    other = VoxelGrid((0.25, 0.25, 0.25), RANGE_MIN + GRID.point_range_max)
    with pytest.raises(MSSFError, match=r"x\.grid: expected the block's grid \(voxel_size \(0\.25, 0\.25, 0\.25\)"):
        FusionBlock(SFF([6, 6], 16), other, downsample=down, blocks=blocks)(voxels, inputs)
    with pytest.raises(TypeError, match="in_stride"):
        FusionBlock(SFF([6, 6], 16), GRID, downsample=down, in_stride=(1, 1, 1))


def test_msdff_takes_in_and_out_channels_like_sff_and_keeps_the_old_keywords():
    new = MSDFF(6, 16, num_heads=2, num_levels=2, num_points=2)
    old = MSDFF(embed_dim=16, value_channels=6, num_heads=2, num_levels=2, num_points=2)
    assert (new.in_channels, new.out_channels) == (SFF([6, 6], 16).in_channels[0], SFF([6, 6], 16).out_channels)
    assert {k: v.shape for k, v in new.state_dict().items()} == {k: v.shape for k, v in old.state_dict().items()}
    assert new.value_proj.weight.shape == (6, 6) and new.output_proj.weight.shape == (16, 6)
    with pytest.raises(MSSFError, match=r"embed_dim: expected either out_channels= or embed_dim="):
        MSDFF(6, 16, embed_dim=16)
    with pytest.raises(MSSFError, match=r"in_channels: expected a positive int"):
        MSDFF(out_channels=16)


def test_the_readme_example_states_each_number_once():
    """The drop-in example's arguments: 9 (16 before issue 43: MSDFF 5, QueryInit 4, FusionBlock 7, with the
    voxel channels stated three times, the image channels twice and the range twice)."""
    import ast
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    code = readme.split("## Drop it into your detector", 1)[1].split("```python", 1)[1].split("```", 1)[0]
    calls = {}
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.Call) and getattr(node.func, "id", "") in ("FusionBlock", "MSDFF", "VoxelGrid", "QueryInit"):
            calls.setdefault(node.func.id, []).append(len(node.args) + len(node.keywords))
    assert "QueryInit" not in calls
    assert sum(n for c in ("FusionBlock", "MSDFF", "VoxelGrid") for n in calls[c]) == 9
    assert "in_stride" not in code and "point_range_min=" not in code


def test_non_finite_voxel_features_are_named_not_an_index_error():
    # a NaN query gives NaN sampling locations; the sampling op's pixel plan once failed on the integer cell
    # INT64_MIN they became ("index -9223372036854775808 is out of bounds"), which named nothing
    voxels, inputs = make_scene(c=8)
    torch.manual_seed(0)
    block = FusionBlock(MSDFF(6, 8, num_heads=2, num_levels=2, num_points=2), GRID).eval()
    features = voxels.features.clone()
    features[0, 0] = float("nan")
    with torch.no_grad(), pytest.raises(MSSFError, match=r"sampling locations: expected finite values, got NaN"):
        block(dataclasses.replace(voxels, features=features), inputs)
