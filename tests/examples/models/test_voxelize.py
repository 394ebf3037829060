import math

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.testing import assert_close
from mssf_examples.models.voxelize import (
    DynamicVoxelizer,
    PillarFeatureNet,
    VoxelGrid,
    dynamic_voxelize,
    pillars_to_bev,
)

GRID = VoxelGrid(voxel_size=(0.5, 0.5, 0.5), point_cloud_range=(0.0, -2.0, -1.0, 4.0, 2.0, 1.0))


def _points(n=200, seed=0, c=5):
    g = torch.Generator().manual_seed(seed)
    p = torch.rand(n, c, generator=g, dtype=torch.float64)
    # span a bit more than the range so some points fall outside
    p[:, 0] = p[:, 0] * 5.0 - 0.5
    p[:, 1] = p[:, 1] * 5.0 - 2.5
    p[:, 2] = p[:, 2] * 2.4 - 1.2
    b = torch.randint(0, 2, (n,), generator=g)
    return p, b


def _naive_groups(points, batch, pcr, vs):
    groups = {}
    for i in range(points.shape[0]):
        x, y, z = points[i, :3].tolist()
        ix = math.floor((x - pcr[0]) / vs[0])
        iy = math.floor((y - pcr[1]) / vs[1])
        iz = math.floor((z - pcr[2]) / vs[2])
        nx = round((pcr[3] - pcr[0]) / vs[0])
        ny = round((pcr[4] - pcr[1]) / vs[1])
        nz = round((pcr[5] - pcr[2]) / vs[2])
        if 0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz:
            groups.setdefault((int(batch[i]), iz, iy, ix), []).append(i)
    return groups


def test_grid_shape_and_divisibility():
    assert GRID.grid_size == (8, 8, 4)
    assert GRID.spatial_shape == (4, 8, 8)
    with pytest.raises(MSSFError, match="not a multiple"):
        VoxelGrid(voxel_size=(0.3, 0.5, 0.5), point_cloud_range=(0, 0, 0, 1.0, 1.0, 1.0))


def test_dynamic_voxelize_matches_naive_loop():
    pts, b = _points()
    vox = dynamic_voxelize(pts, b, 2, GRID)
    groups = _naive_groups(pts, b, GRID.point_cloud_range, GRID.voxel_size)
    assert vox.coords.shape == (len(groups), 4) and vox.coords.dtype == torch.int32
    assert int(vox.keep.sum()) == sum(len(v) for v in groups.values())
    for row, key in enumerate(map(tuple, vox.coords.tolist())):
        idx = groups[key]
        assert_close(vox.features[row], pts[idx].mean(0))
        assert int(vox.num_points[row]) == len(idx)
    # every kept point maps to its own voxel
    kept = torch.nonzero(vox.keep).squeeze(1).tolist()
    for j, i in enumerate(kept):
        assert i in groups[tuple(vox.coords[vox.point_voxel[j]].tolist())]


def test_dynamic_voxelizer_module_returns_sparse_voxels():
    pts, b = _points(seed=1)
    v = DynamicVoxelizer(GRID.point_cloud_range, GRID.voxel_size)(pts, b, 2)
    assert v.spatial_shape == (4, 8, 8) and v.voxel_size == (0.5, 0.5, 0.5)
    # voxel centres lie within half a voxel of every member point
    vox = dynamic_voxelize(pts, b, 2, GRID)
    centres = v.voxel_centers()[vox.point_voxel]
    assert ((pts[vox.keep, :3] - centres).abs() <= 0.25 + 1e-12).all()


def test_voxelize_bad_input():
    pts, b = _points()
    with pytest.raises(MSSFError, match="points_batch"):
        dynamic_voxelize(pts, b + 5, 2, GRID)
    with pytest.raises(MSSFError, match="points"):
        dynamic_voxelize(pts[:, :2], b, 2, GRID)
    bad = pts.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(MSSFError, match="finite"):
        dynamic_voxelize(bad, b, 2, GRID)


def test_empty_points():
    vox = dynamic_voxelize(torch.zeros(0, 4), torch.zeros(0, dtype=torch.long), 1, GRID)
    assert vox.coords.shape == (0, 4) and vox.features.shape == (0, 4)


def test_pillar_feature_net_matches_naive_loop():
    torch.manual_seed(0)
    pts, b = _points(c=5)
    pfn = PillarFeatureNet(5, 8, GRID.point_cloud_range, (0.5, 0.5)).double().eval()
    with torch.no_grad():
        pfn.norm.running_mean.uniform_(-0.5, 0.5)
        pfn.norm.running_var.uniform_(0.5, 2.0)
    out = pfn(pts, b, 2)
    pcr = GRID.point_cloud_range
    groups = _naive_groups(pts, b, pcr, (0.5, 0.5, pcr[5] - pcr[2]))
    assert out.features.shape == (len(groups), 8) and out.spatial_shape == (1, 8, 8)
    w = pfn.linear.weight
    bn = pfn.norm
    for row, key in enumerate(map(tuple, out.coords.tolist())):
        idx = groups[key]
        p = pts[idx]
        mean = p[:, :3].mean(0)
        centre = torch.tensor([(key[3] + 0.5) * 0.5 + pcr[0], (key[2] + 0.5) * 0.5 + pcr[1], 0.0], dtype=p.dtype)
        dec = torch.cat([p, p[:, :3] - mean, p[:, :3] - centre], 1)
        h = dec @ w.T
        h = (h - bn.running_mean) / torch.sqrt(bn.running_var + bn.eps) * bn.weight + bn.bias
        expected = torch.relu(h).max(0).values
        assert_close(out.features[row], expected)


def test_pillar_feature_net_trains_and_backprops():
    pts, b = _points(c=4)
    pfn = PillarFeatureNet(4, 6, GRID.point_cloud_range, (0.5, 0.5))
    out = pfn(pts.float(), b, 2)
    out.features.sum().backward()
    assert pfn.linear.weight.grad is not None and torch.isfinite(pfn.linear.weight.grad).all()
    with pytest.raises(MSSFError, match="columns"):
        pfn(pts[:, :3].float(), b, 2)


def test_pillars_to_bev_matches_loop():
    pts, b = _points(c=4)
    v = DynamicVoxelizer(GRID.point_cloud_range, GRID.voxel_size)(pts, b, 2)
    bev = pillars_to_bev(v)
    ref = torch.zeros(2, 4, 8, 8, dtype=pts.dtype)
    for f, (bb, _, y, x) in zip(v.features, v.coords.tolist()):
        ref[bb, :, y, x] += f
    assert_close(bev, ref)
