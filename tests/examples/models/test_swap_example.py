"""Runs ``examples/swap_openpcdet_stage.py`` (swap OpenPCDet-style conv2 for a FusionBlock)."""

import runpy
from pathlib import Path

import pytest

pytest.importorskip("spconv.pytorch")

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "swap_openpcdet_stage.py"
pytestmark = pytest.mark.spconv


def test_swap_example_runs_and_prints_shapes(capsys):
    namespace = runpy.run_path(str(EXAMPLE))
    shapes = namespace["main"]()
    out = capsys.readouterr().out
    assert "conv2 is a FusionBlock with downsample_stride (2, 2, 2)" in out
    # OpenPCDet's VoxelResBackBone8x grid arithmetic for a (41, 128, 128) input grid.
    assert shapes["input"][1] == (41, 128, 128)
    assert shapes["conv1"] == ((shapes["input"][0][0], 16), (41, 128, 128))
    assert shapes["conv2"][0][1] == 32 and shapes["conv2"][1] == (21, 64, 64)
    assert shapes["conv3"][1] == (11, 32, 32)
    assert shapes["conv4"][1] == (5, 16, 16)
    assert shapes["conv_out"][1] == (2, 16, 16)


def test_swapped_stage_changes_only_seen_voxels():
    ns = runpy.run_path(str(EXAMPLE))
    import torch

    torch.set_num_threads(1)
    feats, coords, inputs = ns["random_frame"](seed=1)
    lo, hi = torch.tensor(ns["POINT_CLOUD_RANGE"][:3]), torch.tensor(ns["POINT_CLOUD_RANGE"][3:])
    grid = ((hi - lo) / torch.tensor(ns["VOXEL_SIZE"])).round().long().tolist()
    backbone = ns["VoxelResBackBone8x"](feats.shape[1], grid).eval()
    with torch.no_grad():
        x = backbone.conv1(backbone.conv_input(ns["spconv"].SparseConvTensor(feats, coords, backbone.sparse_shape, 2)))
        plain = backbone.conv2[0](x)  # the stage's own downsample block
        block = ns["swap_conv2_for_fusion"](backbone)
        block.blocks = None  # look at f_fuse right after the fusion step
        fused = block(x, inputs)
    assert torch.equal(fused.indices, plain.indices)
    changed = (fused.features != plain.features).any(1)
    assert changed.any() and (~changed).any()  # the camera sees only the front part of the scene
    from mssf_blocks.sparse_voxels import SparseVoxels

    vox = SparseVoxels.from_spconv(plain, voxel_size=ns["VOXEL_SIZE"], point_range_min=ns["POINT_CLOUD_RANGE"][:3], stride=(2, 2, 2))
    proj = block.projector(vox, inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size)
    assert torch.equal(changed, proj.valid.any(1))
