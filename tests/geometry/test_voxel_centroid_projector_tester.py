"""VoxelCentroidProjector through the shared block checks (``tests/helpers/block_tester.py``): a hand-worked
projection (a voxel with points, an empty one at its centre) on every device and the float64 gradcheck of
the projection under it (``project_points``). The projector's other behaviour:
``test_voxel_centroid_projector.py``. (No state-dict round trip: the projector holds no tensors.)"""

import sys
from pathlib import Path

import torch

from mssf_blocks import CentroidProjection, MSSFError, SparseVoxels, VoxelCentroidProjector, augmentation_matrix

from block_tester import BlockTester, Reference

sys.path.insert(0, str(Path(__file__).parent))
from test_voxel_centroid_projector import l2i_front  # noqa: E402


def _project(proj, vox, pts, batch, l2i):
    out = proj(vox, pts, batch, l2i, (12, 16))
    assert isinstance(out, CentroidProjection)
    assert out.uv.shape == (2, 1, 2) and out.valid.shape == (2, 1) and out.num_cameras == 1
    return out.centroid[0], out.centroid[1], out.has_points, out.uv[0, 0], out.depth[0, 0], out.batch_index


class TestVoxelCentroidProjector(BlockTester):
    def reference(self, case):
        # Grid: voxel 1 m, range min (0, -2, -1), shape (D, H, W) = (2, 4, 4).
        coords = torch.tensor([[0, 1, 2, 2], [0, 0, 0, 3]], dtype=torch.int32)
        vox = SparseVoxels(torch.zeros(2, 3, dtype=torch.float64), coords, (2, 4, 4), 1, voxel_size=(1.0, 1.0, 1.0), point_range_min=(0.0, -2.0, -1.0))
        # Two points in voxel (z=1, y=2, x=2): x in [2, 3), y in [0, 1), z in [0, 1). Their mean: (2.5, 0.25, 0.5).
        pts = torch.tensor([[2.2, 0.1, 0.4], [2.8, 0.4, 0.6]], dtype=torch.float64)
        expected = (
            torch.tensor([2.5, 0.25, 0.5], dtype=torch.float64),
            # Empty voxel (z=0, y=0, x=3) uses its centre (3.5, -1.5, -0.5).
            torch.tensor([3.5, -1.5, -0.5], dtype=torch.float64),
            torch.tensor([True, False]),
            # Centroid (2.5, 0.25, 0.5): u = 8 - 10 * 0.25 / 2.5 = 7, v = 6 - 10 * 0.5 / 2.5 = 4.
            torch.tensor([7.5 / 16, 4.5 / 12], dtype=torch.float64),
            torch.tensor(2.5, dtype=torch.float64),
            torch.tensor([0, 0]),
        )
        return Reference(VoxelCentroidProjector(),
                         lambda d: (vox.to(d), pts.to(d), torch.zeros(2, dtype=torch.long, device=d), l2i_front().to(d)),
                         _project, expected)

    def gradcheck(self, case):
        from mssf_blocks.functional.geometry import project_points

        pts = torch.tensor([[3.0, 0.5, 0.2], [4.0, -0.3, -0.1], [-2.0, 0.0, 0.0]], dtype=torch.float64)
        batch = torch.zeros(3, dtype=torch.long)

        def fn(p, m):
            o = project_points(p, batch, m, (12, 16))
            return o.uv, o.depth

        return fn, [pts, l2i_front()]
