"""The inputs the runnable doc blocks assume (``test_docs_snippets.py``): a pinhole front camera, radar
points, FPN levels, spconv input, a VoD-preset batch, OpenPCDet's ``conv2``, a one-camera scene with a
car box, a tree of symlinks to real frames.
"""

from __future__ import annotations

import types
from pathlib import Path
from typing import Dict, Optional, Tuple

import pytest
import torch


# ---------------------------------------------------------------------------------------------------
# shared scene: one front camera (x forward, y left, z up), VoD-like range and voxels
# ---------------------------------------------------------------------------------------------------
VOD_RANGE = (0.0, -25.6, -3.0, 51.2, 25.6, 2.0)
VOD_VOXEL = (0.05, 0.05, 0.125)


def pinhole(batch_size: int, image_size: Tuple[int, int], f: float) -> torch.Tensor:
    """``(B, 1, 3, 4)`` lidar2img of a camera at the origin looking along +x, principal point at the centre."""
    h, w = image_size
    k = torch.tensor([[f, 0.0, (w - 1) / 2], [0.0, f, (h - 1) / 2], [0.0, 0.0, 1.0]])
    sensor_to_cam = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])  # (right, down, forward)
    return (k @ sensor_to_cam).expand(batch_size, 1, 3, 4).contiguous()


def radar_points(batch_size: int = 2, per_sample: int = 60, seed: int = 0) -> torch.Tensor:
    """``(P, 1 + 7)`` OpenPCDet-style points ``[b, x, y, z, RCS, v_r, v_rc, t]`` in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    rows = []
    for b in range(batch_size):
        xyz = torch.rand(per_sample, 3, generator=g) * torch.tensor([25.0, 10.0, 3.0]) + torch.tensor([5.0, -5.0, -2.5])
        rows.append(torch.cat([torch.full((per_sample, 1), float(b)), xyz, torch.randn(per_sample, 4, generator=g)], 1))
    return torch.cat(rows)


def voxel_coords(points: torch.Tensor, voxel_size, point_range_min) -> torch.Tensor:
    """Unique ``(b, z, y, x)`` int32 base-grid voxels of ``points`` (``[b, x, y, z, ...]`` rows)."""
    idx = ((points[:, 1:4] - torch.tensor(point_range_min)) / torch.tensor(voxel_size)).floor().long()
    return torch.unique(torch.cat([points[:, :1].long(), idx.flip(1)], 1), dim=0).int()


def fpn(batch_size: int, image_size, channels: int = 256, strides=(4, 8, 16, 32), cameras: Optional[int] = None, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    h, w = image_size
    lead = (batch_size,) if cameras is None else (batch_size, cameras)
    return [torch.randn(*lead, channels, h // s, w // s, generator=g) for s in strides]


def spconv_input(points: torch.Tensor, channels: int, spatial_shape, batch_size: int, seed: int = 2):
    spconv = pytest.importorskip("spconv.pytorch")
    coords = voxel_coords(points, VOD_VOXEL, VOD_RANGE[:3])
    feats = torch.randn(coords.shape[0], channels, generator=torch.Generator().manual_seed(seed))
    return spconv.SparseConvTensor(feats, coords, list(spatial_shape), batch_size)


def vod_batch(batch_size: int = 2):
    """A RadarCameraBatch for the VOD preset: 7-feature points, boxes, 4 precomputed FPN levels."""
    from mssf_examples.data.batch import RadarCameraBatch

    image_size = (1216, 1936)
    pts = radar_points(batch_size, per_sample=80, seed=3)
    points = [pts[pts[:, 0] == b, 1:] for b in range(batch_size)]
    boxes = [torch.tensor([[10.0, 0.0, -1.0, 3.9, 1.6, 1.56, 0.3], [15.0, 3.0, -1.0, 0.8, 0.6, 1.73, 0.0]])] * batch_size
    labels = [torch.tensor([0, 1])] * batch_size
    return RadarCameraBatch(points=points, lidar2img=pinhole(batch_size, image_size, 1495.5),
                            image_features=fpn(batch_size, image_size, strides=(16, 32, 64, 128), cameras=1),
                            image_size=image_size, gt_boxes=boxes, gt_labels=labels)


def openpcdet_conv2(spconv, nn):
    """OpenPCDet VoxelBackBone8x ``conv2``: three post-act blocks, the first a stride-2 SparseConv3d."""

    def block(conv, c):
        return spconv.SparseSequential(conv, nn.BatchNorm1d(c), nn.ReLU())

    return spconv.SparseSequential(
        block(spconv.SparseConv3d(16, 32, 3, stride=2, padding=1, bias=False, indice_key="spconv2"), 32),
        block(spconv.SubMConv3d(32, 32, 3, padding=1, bias=False, indice_key="subm2"), 32),
        block(spconv.SubMConv3d(32, 32, 3, padding=1, bias=False, indice_key="subm2"), 32),
    )


def run_detectors_init(run_block):
    spconv = pytest.importorskip("spconv.pytorch")
    from torch import nn

    ns = {"spconv": spconv, "self": types.SimpleNamespace(conv2=openpcdet_conv2(spconv, nn)), "point_cloud_range": VOD_RANGE}
    return run_block(ns)


def camera_scene(channels: int = 8, stride: int = 1):
    """One sample, one camera (64 x 96 image, f = 40 px); a car box at x = 10 m, points:

    0: inside the box (3D foreground); 1: 10 m behind the box, in its 2D box (3D-blurred);
    2: beside the box, outside its 2D box (background); 3: inside the box, near point 0.
    """
    from mssf_blocks import SparseVoxels, VoxelCentroidProjector
    from mssf_blocks.heads import points_in_boxes

    image_size = (64, 96)
    lidar2img = pinhole(1, image_size, 40.0)
    points = torch.tensor([[10.0, 0.1, 0.1], [20.0, 0.1, 0.1], [10.0, 9.0, 0.1], [10.6, 0.3, 0.4]])
    points_batch = torch.zeros(4, dtype=torch.long)
    gt_boxes = [torch.tensor([[10.0, 0.0, 0.0, 4.0, 2.0, 2.0, 0.0]])]
    # 2D box: the projected corners' bounding box.
    corners = torch.tensor([[x, y, z] for x in (8, 12) for y in (-1, 1) for z in (-1, 1)], dtype=torch.float32)
    uvd = torch.cat([corners, torch.ones(8, 1)], 1) @ lidar2img[0, 0].T
    uv = uvd[:, :2] / uvd[:, 2:]
    gt_boxes_2d = [torch.cat([uv.min(0).values, uv.max(0).values])[None]]
    vs = (0.5, 0.5, 0.5)
    lo = (0.0, -10.0, -2.0)
    idx = ((points - torch.tensor(lo)) / (torch.tensor(vs) * stride)).floor().int()
    coords = torch.unique(torch.cat([torch.zeros(4, 1, dtype=torch.int32), idx.flip(1)], 1), dim=0)
    voxels = SparseVoxels(torch.randn(coords.shape[0], channels, generator=torch.Generator().manual_seed(0)), coords,
                          (8 // stride, 40 // stride, 60 // stride), 1, voxel_size=vs, point_range_min=lo, stride=(stride,) * 3)
    assert points_in_boxes(points, gt_boxes[0])[:, 0].tolist() == [True, False, False, True]
    return dict(projector=VoxelCentroidProjector(), voxels=voxels, points=points, points_batch=points_batch,
                lidar2img=lidar2img, image_size=image_size, gt_boxes=gt_boxes, gt_boxes_2d=gt_boxes_2d)


def link_tree(dst: Path, files: Dict[str, Path]) -> None:
    """Under ``dst``, per ``sub: src`` of ``files``: a folder ``sub`` of symlinks to the files of ``src``."""
    for sub, src in files.items():
        (dst / sub).mkdir(parents=True, exist_ok=True)
        for f in src.iterdir():
            (dst / sub / f.name).symlink_to(f)
