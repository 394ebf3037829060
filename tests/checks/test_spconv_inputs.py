"""Issue 33, item 5: what spconv (or BatchNorm) would fail on with its own error gets ours first."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

from mssf_blocks import SparseVoxels, VoxelGrid
from mssf_blocks.checks.spconv_inputs import check_spconv_input
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import SFF
from mssf_blocks.geometry import CentroidProjection

pytestmark = pytest.mark.usefixtures("one_thread")


def voxels(n=3, dtype=torch.float32):
    coords = torch.tensor([[0, 0, 1, 2], [0, 1, 2, 3], [0, 2, 3, 7]], dtype=torch.int32)[:n]
    return SparseVoxels(torch.ones(n, 4, dtype=dtype), coords, (4, 8, 8), 1, voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))


def test_integer_features_are_refused_before_spconv():
    v = voxels()
    with pytest.raises(MSSFError, match=r"features: expected a floating dtype.*got torch.int64.*\.float\(\)"):
        check_spconv_input(v.features.long(), v.coords, v.spatial_shape, 1)


def test_zero_voxels_are_refused_before_spconv():
    with pytest.raises(MSSFError, match=r"at least one voxel for spconv, got 0"):
        voxels(0).to_spconv()


def test_int64_indices_are_refused_before_spconv():
    v = voxels()
    with pytest.raises(MSSFError, match=r"coords: expected dtype torch.int32.*int64.*\.int\(\)"):
        check_spconv_input(v.features, v.coords.long(), v.spatial_shape, 1)


def test_permuted_spatial_shape_is_named():
    # SparseVoxels: coordinates that fit only a permutation of the grid say so
    coords = torch.tensor([[0, 1, 2, 12]], dtype=torch.int32)  # x = 12 needs W >= 13
    with pytest.raises(MSSFError, match=r"x index.*fit spatial_shape=\(4, 8, 16\).*\(D, H, W\)"):
        SparseVoxels(torch.ones(1, 4), coords, (16, 8, 4), 1, voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))
    v = voxels()
    with pytest.raises(MSSFError, match=r"expected the network's \(4, 8, 16\), got \(16, 8, 4\).*permuted"):
        check_spconv_input(v.features, v.coords, (16, 8, 4), 1, expected_shape=(4, 8, 16))


def test_one_visible_voxel_in_training_mode_is_our_error():
    sff = SFF([4], 6).train()
    n = 5
    valid = torch.zeros(n, 1, dtype=torch.bool)
    valid[2] = True
    proj = CentroidProjection(uv=torch.full((n, 1, 2), 0.5), depth=torch.ones(n, 1), valid=valid,
                              centroid=torch.zeros(n, 3), has_points=torch.ones(n, dtype=torch.bool),
                              batch_index=torch.zeros(n, dtype=torch.long))
    with pytest.raises(MSSFError, match=r"exactly one of the 5 voxels is visible.*BatchNorm1d.*eval"):
        sff([torch.randn(1, 4, 8, 8)], proj)
    assert sff.eval()([torch.randn(1, 4, 8, 8)], proj).shape == (n, 6)  # eval: fine


def _block(point_range_max=None):
    from mssf_blocks import VoxelCentroidProjector
    from mssf_blocks.blocks import FusionBlock

    grid = (VoxelGrid.covering((0.1, 0.1, 0.2), (0.0, 0.0, 0.0), (4, 8, 8)) if point_range_max is None
            else VoxelGrid((0.1, 0.1, 0.2), (0.0, 0.0, 0.0) + tuple(point_range_max)))
    return FusionBlock(SFF([4], 4), grid=grid,
                       projector=VoxelCentroidProjector(point_range_max=point_range_max))


def test_spatial_shape_against_the_metric_grid_names_the_order():
    from mssf_blocks.samplers import FusionInputs

    # range 1.6 x 0.8 x 0.8 m over voxels (0.1, 0.1, 0.2): (D, H, W) = (4, 8, 16)
    block = _block((1.6, 0.8, 0.8))
    inputs = FusionInputs([torch.zeros(1, 4, 8, 8)], torch.eye(3, 4)[None], (8, 8), torch.zeros(0, 3),
                          torch.zeros(0, dtype=torch.long))
    coords = torch.tensor([[0, 1, 2, 3]], dtype=torch.int32)
    wrong = SparseVoxels(torch.ones(1, 4), coords, (16, 8, 4), 1, voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))
    with pytest.raises(MSSFError, match=r"spatial_shape: expected \(D, H, W\) = \(4.0, 8.0, 16.0\).*got \(16, 8, 4\)"
                                        r".*\(4, 8, 16\) would fit"):
        block(wrong, inputs)
    right = SparseVoxels(torch.ones(1, 4), coords, (4, 8, 16), 1, voxel_size=(0.1, 0.1, 0.2), point_range_min=(0.0, 0.0, 0.0))
    block.eval()(right, inputs)


def test_spconv_indices_outside_a_permuted_spatial_shape_are_named():
    spconv = pytest.importorskip("spconv.pytorch")
    from mssf_blocks.samplers import FusionInputs

    inputs = FusionInputs([torch.zeros(1, 4, 8, 8)], torch.eye(3, 4)[None], (8, 8), torch.zeros(0, 3),
                          torch.zeros(0, dtype=torch.long))
    idx = torch.tensor([[0, 1, 2, 12], [0, 3, 7, 15]], dtype=torch.int32)  # x up to 15: W = 16
    x = spconv.SparseConvTensor(torch.ones(2, 4), idx, [16, 8, 4], 1)  # (W, H, D) given
    with pytest.raises(MSSFError, match=r"indices: expected .* inside spatial_shape \(16, 8, 4\).*\(4, 8, 16\)"):
        _block()(x, inputs)


def test_float64_on_several_cpu_threads_is_refused_before_spconv():
    v = voxels(dtype=torch.float64)
    check_spconv_input(v.features, v.coords, v.spatial_shape, 1)  # one thread (the fixture): accepted
    n = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        with pytest.raises(MSSFError, match=r"features: float64 on the CPU needs one torch thread.*got 2.*float32"):
            v.to_spconv()
        check_spconv_input(v.features.float(), v.coords, v.spatial_shape, 1)  # float32: accepted
    finally:
        torch.set_num_threads(n)


# Whether the race shows depends on the problem's size and on the machine's load: on the developers' 2-core host
# (session 52) 400 voxels gave 0 wrong draws of 20 on an idle machine and 18 of 20 beside a busy process, 4,000
# voxels 20 of 20 idle and 12 of 20 busy; one CI run saw 20 draws of the small size agree. So the probe cycles
# through three sizes and stops at the first wrong draw.
_TWO_THREADS = """
import torch, spconv.pytorch as spconv
gen = torch.Generator().manual_seed(0)
worst = 0.0
for draw in range(60):
    points, side = ((400, 20), (2000, 30), (4000, 40))[draw % 3]
    idx = torch.unique(torch.randint(0, side, (points, 3), generator=gen), dim=0)
    coords = torch.cat([torch.zeros(len(idx), 1, dtype=torch.int64), idx], 1).int()
    feats = torch.randn(len(idx), 16, dtype=torch.float64, generator=gen)
    conv = spconv.SubMConv3d(16, 32, 3, indice_key="t", bias=False).double()
    out = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        out.append(conv(spconv.SparseConvTensor(feats, coords, [side] * 3, 1)).features)
    worst = max(worst, (out[0] - out[1]).abs().max().item())
    if worst > 1e-6:
        break
print(worst, draw + 1)
"""

# The spconv release whose float64 CPU results were measured wrong on two threads (the check above exists for it).
_KNOWN_WRONG = "2.3.8"


def test_spconv_float64_on_two_threads_is_still_wrong():
    """Why the check above exists; when a newer spconv is right on two threads, this fails: drop the check.

    Run in a fresh interpreter: inside the whole suite one CI run saw five draws agree (what earlier tests
    leave behind can keep the second thread from running alongside the first). The race is a matter of
    chance: where it does not show within the probe's draws on the release known to be wrong, the test skips
    and says so; on any other release an unseen race fails it, so that the upgrade is looked at."""
    pytest.importorskip("spconv.pytorch")
    from importlib.metadata import version

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one CPU core available: two torch threads cannot run at once, so the race cannot be probed")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    done = subprocess.run([sys.executable, "-c", _TWO_THREADS], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    worst, draws = done.stdout.split()[-2:]
    if float(worst) > 1e-6:
        return
    seen = f"spconv's float64 CPU results agree on one and two threads ({draws} draws, max diff {worst})"
    if version("spconv") == _KNOWN_WRONG:
        pytest.skip(f"{seen}: the race did not show this time on spconv {_KNOWN_WRONG}, the release known to be wrong")
    pytest.fail(f"{seen} on spconv {version('spconv')}: if it is right now, drop check_spconv_input's thread check")
