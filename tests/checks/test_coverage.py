"""Issue 33, item 1: a coverage that collapses against its running value (not only to zero) warns.

The scenes are :mod:`test_geometry_sanity`'s (a VoD-like camera ``K @ [R | t]``, points in front of it,
the voxels holding them): correct frames first (the projector's running values), then a frame with a
mistake that cuts the in-image or the centroid fraction without zeroing it. Each mistake is shown to
pass the per-sample zero checks; since issue 42 the first-call consistency checks (``_first_call``,
tests/checks/test_first_call.py) name it on a fresh projector too, and the running value still warns
beside them (both messages are asserted).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import pytest
import torch

from mssf_blocks import SparseVoxels, VoxelCentroidProjector
from mssf_blocks.errors import MSSFGeometryWarning
from mssf_blocks.geometry import augmentation_matrix
from mssf_blocks.checks import set_geometry_checks

sys.path.insert(0, str(Path(__file__).parent))
from test_geometry_sanity import LO, SHAPE, VOXEL, scene  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
WIDE_LO = (-50.0, -50.0, -3.0)  # a grid that holds the rotated scenes


def first_call(msgs, prefix):
    """The one first-call consistency message (issue 42) starting with ``prefix``, and the others."""
    mine = [m for m in msgs if m.startswith(prefix)]
    assert len(mine) == 1, msgs
    return [m for m in msgs if not m.startswith(prefix)]


def run(projector, vox, pts, pb, l2i, pts2s=None):
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        out = projector(vox, pts, pb, l2i, (480, 640), pts2s)
    return out, [str(w.message) for w in got if issubclass(w.category, MSSFGeometryWarning)]


def rotated(rotation: float, seed: int):
    """The scene turned by ``rotation`` (global augmentation), voxelised in the augmented frame."""
    _, pts, pb, l2i = scene(seed=seed)
    aug = augmentation_matrix(rotation=rotation).float()
    pts_aug = (torch.cat([pts, torch.ones(len(pts), 1)], 1) @ aug.T)[:, :3]
    idx = ((pts_aug.double() - torch.tensor(WIDE_LO, dtype=torch.float64))
           / torch.tensor(VOXEL, dtype=torch.float64)).floor().long()
    cells = torch.unique(torch.stack([idx[:, 2], idx[:, 1], idx[:, 0]], 1), dim=0)
    coords = torch.cat([torch.zeros(len(cells), 1, dtype=torch.long), cells], 1).int()
    vox = SparseVoxels(torch.zeros(len(cells), 4), coords, (30, 480, 240), 1, voxel_size=VOXEL, point_range_min=WIDE_LO)
    return vox, pts_aug, pb, l2i, aug


def warmed(frames=10):
    """A projector that has seen ``frames`` correct augmented frames (rotations within +-0.5 rad): quiet."""
    proj = VoxelCentroidProjector()
    for i in range(frames):
        vox, pts, pb, l2i, aug = rotated(0.5 * (-1) ** i * (i % 3) / 2, seed=10 + i)
        out, msgs = run(proj, vox, pts, pb, l2i, torch.linalg.inv(aug)[None])
        assert msgs == [] and out.valid.all(), (i, msgs)
    return proj


def test_forward_augmentation_that_only_cuts_the_in_image_fraction_warns_against_the_running_value():
    vox, pts, pb, l2i, aug = rotated(0.5, seed=3)
    wrong = aug[None]  # the forward matrix as points_to_sensor: the 0.5 rad rotation doubled
    out, msgs = run(VoxelCentroidProjector(), vox, pts, pb, l2i, wrong)
    frac = out.valid.float().mean().item()
    # some voxels still in view: the zero check is silent (the first-call check names points_to_sensor)
    assert 0.0 < frac < 0.25 and first_call(msgs, "points_to_sensor:") == []
    proj = warmed()
    seen, mean = proj.coverage.running("projection", (1, 1, 1))
    assert seen == 10 and mean == 1.0
    _, msgs = run(proj, vox, pts, pb, l2i, wrong)
    msgs = first_call(msgs, "points_to_sensor:")
    assert len(msgs) == 1, msgs
    m = msgs[0]
    assert m.startswith("projection: sample 0's in-image fraction") and f"{frac:.3f}" in m, m
    assert "running value 1.000" in m and "points_to_sensor" in m and "inverse" in m, m
    # warned once per projector: the next collapsed frame is quiet, a fresh projector warns again
    assert first_call(run(proj, vox, pts, pb, l2i, wrong)[1], "points_to_sensor:") == []
    proj.coverage.reset()
    assert proj.coverage.running("projection", (1, 1, 1)) == (0, 0.0)


def test_a_drop_within_the_threshold_is_quiet():
    vox, pts, pb, l2i, aug = rotated(0.2, seed=3)  # doubled to 0.4 rad: ~60 % still in view
    proj = warmed()
    out, msgs = run(proj, vox, pts, pb, l2i, aug[None])
    # quiet against the running value; the first-call check compares with the inverse matrix and names it
    assert 0.25 < out.valid.float().mean().item() < 0.9 and first_call(msgs, "points_to_sensor:") == []


def test_point_range_min_a_voxel_off_collapses_the_centroid_fraction():
    vox, pts, pb, l2i = scene(seed=3)
    shifted = SparseVoxels(vox.features, vox.coords, SHAPE, 1, voxel_size=VOXEL, point_range_min=(LO[0], LO[1] + VOXEL[1], LO[2]))
    out, msgs = run(VoxelCentroidProjector(), shifted, pts, pb, l2i)
    # a few neighbours: not zero (the zero check is silent; the first-call points-in-voxels check names it)
    assert 0.0 < out.has_points.float().mean().item() < 0.05 and first_call(msgs, "points: only") == []
    proj = VoxelCentroidProjector()
    for seed in range(8):
        assert run(proj, *scene(seed=10 + seed))[1] == []
    _, msgs = run(proj, shifted, pts, pb, l2i)
    msgs = first_call(msgs, "points: only")
    assert len(msgs) == 1 and msgs[0].startswith("centroids: sample 0's centroid fraction"), msgs
    assert "running value 1.000" in msgs[0] and "point_range_min" in msgs[0], msgs


def test_points_labelled_with_another_sample_warn_for_the_sample_left_without_points():
    (v0, p0, b0, l0), (v1, p1, b1, l1) = scene(seed=1), scene(seed=2)
    coords = torch.cat([v0.coords, v1.coords + torch.tensor([1, 0, 0, 0], dtype=torch.int32)])
    vox = SparseVoxels(torch.zeros(len(coords), 4), coords, SHAPE, 2, voxel_size=VOXEL, point_range_min=LO)
    pts, l2i = torch.cat([p0, p1]), torch.cat([l0, l1])
    right = torch.cat([b0, b1 + 1])
    wrong = torch.zeros_like(right)  # every point labelled sample 0: sample 1 has voxels and no points
    out, msgs = run(VoxelCentroidProjector(), vox, pts, wrong, l2i)
    # the zero check is silent (sample 1 has no points); the first-call check names points_batch
    assert not out.has_points[out.batch_index == 1].any() and first_call(msgs, "points_batch: sample 1 has") == []
    proj = VoxelCentroidProjector()
    for _ in range(4):  # 8 samples
        assert run(proj, vox, pts, right, l2i)[1] == []
    _, msgs = run(proj, vox, pts, wrong, l2i)
    msgs = first_call(msgs, "points_batch: sample 1 has")
    assert len(msgs) == 1 and "sample 1's centroid fraction is 0.000" in msgs[0], msgs
    assert "points_batch" in msgs[0]


def test_running_values_are_kept_per_stride_and_only_where_the_checks_run():
    vox, pts, pb, l2i = scene(seed=1)
    proj = VoxelCentroidProjector()
    set_geometry_checks(False)  # (on an accelerator this is the default: nothing is read back)
    try:
        run(proj, vox, pts, pb, l2i)
    finally:
        set_geometry_checks(None)
    assert proj.coverage.running("projection", (1, 1, 1)) == (0, 0.0)
    run(proj, vox, pts, pb, l2i)
    n_in = int(run(VoxelCentroidProjector(), vox, pts, pb, l2i)[0].valid.sum())
    assert proj.coverage.running("projection", (1, 1, 1)) == (1, n_in / len(vox.coords))
    assert proj.coverage.running("projection", (2, 2, 2)) == (0, 0.0)
    assert "coverage" not in "".join(proj.state_dict())  # not saved with the weights
