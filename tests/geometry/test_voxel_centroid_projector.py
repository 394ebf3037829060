"""VoxelCentroidProjector: the module over voxel_centroids + project_points."""

import pytest
import torch

from mssf_blocks import CentroidProjection, MSSFError, SparseVoxels, VoxelCentroidProjector, augmentation_matrix
from mssf_blocks.testing import gradcheck64


def l2i_front(batch=1):
    # Sensor x forward -> camera z; f = 10 px, principal point (8, 6); image 12 x 16 (H x W).
    m = torch.tensor([[8.0, -10.0, 0.0, 0.0], [6.0, 0.0, -10.0, 0.0], [1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    return m.expand(batch, 3, 4).clone()


# the hand-worked projection on every device and project_points' float64 gradcheck: the shared block
# checks, test_voxel_centroid_projector_tester.py.


def test_module_batch_mismatch_and_type_errors():
    vox = SparseVoxels(torch.zeros(1, 3), torch.zeros(1, 4, dtype=torch.int32), (2, 4, 4), 2, voxel_size=(1, 1, 1), point_range_min=(0, 0, 0))
    proj = VoxelCentroidProjector()
    pts, pb = torch.zeros(1, 3), torch.zeros(1, dtype=torch.long)
    with pytest.raises(MSSFError, match=r"lidar2img: expected batch size 2 \(voxels.batch_size\)"):
        proj(vox, pts, pb, l2i_front(1).float(), (12, 16))
    with pytest.raises(MSSFError, match=r"points_to_sensor: expected shape \(2, 4, 4\)"):
        proj(vox, pts, pb, l2i_front(2).float(), (12, 16), points_to_sensor=torch.eye(4)[None])
    with pytest.raises(MSSFError, match="voxels: expected SparseVoxels"):
        proj(torch.zeros(3), pts, pb, l2i_front(2).float(), (12, 16))
    with pytest.raises(MSSFError, match="eps"):
        VoxelCentroidProjector(eps=-1.0)


def test_module_augmented_equals_unaugmented():
    g = torch.Generator().manual_seed(1)
    pts = torch.rand(40, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 3.0, 1.5]) + torch.tensor([1.0, -1.5, -0.75])
    batch = torch.zeros(40, dtype=torch.long)
    voxel, lo, shape = (0.5, 0.5, 0.5), (0.0, -4.0, -2.0), (8, 16, 16)

    def voxelise(p):
        idx = torch.floor((p - torch.tensor(lo, dtype=torch.float64)) / torch.tensor(voxel, dtype=torch.float64)).long()
        return torch.unique(torch.cat([batch[:, None], idx[:, [2, 1, 0]]], 1), dim=0).int()

    plain_vox = SparseVoxels(torch.zeros(0, 1, dtype=torch.float64).expand(0, 1), torch.zeros(0, 4, dtype=torch.int32), shape, 1, voxel_size=voxel, point_range_min=lo)
    coords = voxelise(pts)
    plain_vox = plain_vox.replace(coords=coords, features=torch.zeros(len(coords), 1, dtype=torch.float64))
    proj = VoxelCentroidProjector()
    ref = proj(plain_vox, pts, batch, l2i_front(), (12, 16))
    # Augment only by a translation that keeps the voxel partition (whole voxels) and a flip about y=0
    # mapped to whole voxels too: then the augmented voxels hold the same point sets.
    aug = augmentation_matrix(flip_x=True, translation=(1.0, 0.0, 0.0))
    hom = torch.cat([pts, torch.ones(40, 1, dtype=torch.float64)], 1)
    pts_aug = (hom @ aug.T)[:, :3]
    coords_aug = voxelise(pts_aug)
    vox_aug = plain_vox.replace(coords=coords_aug, features=torch.zeros(len(coords_aug), 1, dtype=torch.float64))
    out = proj(vox_aug, pts_aug, batch, l2i_front(), (12, 16), points_to_sensor=torch.linalg.inv(aug)[None])
    # Match voxels through their (un-augmented) centroids.
    key_ref = {tuple(round(v, 9) for v in c): i for i, c in enumerate(ref.centroid.tolist())}
    back = (torch.cat([out.centroid, torch.ones(len(out.centroid), 1, dtype=torch.float64)], 1) @ torch.linalg.inv(aug).T)[:, :3]
    order = [key_ref[tuple(round(v, 9) for v in c)] for c in back.tolist()]
    torch.testing.assert_close(out.uv, ref.uv[order], rtol=1e-10, atol=1e-10)
    assert torch.equal(out.valid, ref.valid[order])
