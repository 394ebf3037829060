"""Realistic mistakes found by an independent pass over the README / docs examples (issue 42), each one
silently wrong before: the batch-index column of OpenPCDet's points read as x, box yaw in degrees, the
head's scores passed as logits, a QueryInit range of another grid. Each test fails on the code before
its check; the no-mistake twins guard against false alarms."""

from __future__ import annotations

import contextlib
import math
import warnings

import pytest
import torch
from torch import nn

from mssf_blocks import FusionBlock, FusionInputs, MSDFF, QueryInit, SemanticGuidedHead, SparseVoxels, VoxelGrid
from mssf_blocks.errors import MSSFError, MSSFGeometryWarning
from mssf_blocks.functional.geometry import voxel_centroids
from mssf_blocks.functional.heads import points_in_boxes, voxel_foreground_labels
from mssf_blocks.functional.lift import voxelize_points
from mssf_blocks.checks import set_geometry_checks

PC_MIN, PC_MAX = (0.0, -25.6, -3.0), (51.2, 25.6, 2.0)


def _cloud(b=2, n=100, seed=0):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(b * n, 3, generator=g) * torch.tensor([25.0, 10.0, 3.0]) + torch.tensor([5.0, -5.0, -2.5])
    batch = torch.arange(b).repeat_interleave(n)
    return xyz, batch


@pytest.fixture(autouse=True)
def _default_checks():
    set_geometry_checks(None)
    yield
    set_geometry_checks(None)


@contextlib.contextmanager
def _no_mssf_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error", MSSFGeometryWarning)
        yield


# --- OpenPCDet's (b, x, y, z, ...) points where (x, y, z, ...) rows are expected ---------------------------
def test_voxelize_points_refuses_a_batch_index_column():
    xyz, batch = _cloud()
    pts = torch.cat([batch[:, None].float(), xyz, torch.rand(len(xyz), 1)], 1)  # OpenPCDet: b, x, y, z, rcs
    with pytest.raises(MSSFError, match=r"column 0 equals points_batch .*OpenPCDet's \(b, x, y, z, \.\.\.\)"):
        voxelize_points(pts, batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    # one sample (all indices 0) is the same mistake
    with pytest.raises(MSSFError, match="column 0 equals points_batch"):
        voxelize_points(pts[batch == 0], batch[batch == 0], 1, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)


def test_voxel_centroids_refuses_a_batch_index_column():
    xyz, batch = _cloud()
    vox = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    pts = torch.cat([batch[:, None].float(), xyz], 1)
    with pytest.raises(MSSFError, match="column 0 equals points_batch"):
        voxel_centroids(pts, batch, vox.coords, vox.spatial_shape, 2, vox.voxel_size, vox.point_range_min)


def test_points_with_feature_columns_and_the_gate():
    xyz, batch = _cloud()
    pts = torch.cat([xyz, torch.rand(len(xyz), 2)], 1)  # x, y, z, rcs, v: accepted
    vox = voxelize_points(pts, batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    ref = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    assert torch.equal(vox.coords, ref.coords)
    # fewer than 8 rows: no verdict (a toy cloud at x = 0)
    toy = torch.tensor([[0.0, 1.0, 1.0, 0.5]] * 7)
    voxelize_points(toy, torch.zeros(7, dtype=torch.long), 1, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    # the data check is gated like the warnings
    set_geometry_checks(False)
    voxelize_points(torch.cat([batch[:, None].float(), xyz], 1), batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)


# --- box yaw in degrees ------------------------------------------------------------------------------------
def _centroids():
    xyz, batch = _cloud()
    return xyz, batch


def test_gt_boxes_with_yaw_in_degrees_warn():
    cent, batch = _centroids()
    boxes = [torch.tensor([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 90.0]]), torch.zeros(0, 7)]
    with pytest.warns(MSSFGeometryWarning, match=r"gt_boxes\[0\]: yaw .* up to 90 .*degrees\? pass radians"):
        voxel_foreground_labels(cent, batch, boxes)
    with pytest.warns(MSSFGeometryWarning, match=r"boxes: yaw .* degrees\?"):
        points_in_boxes(cent, boxes[0])
    head = SemanticGuidedHead(4)
    with pytest.warns(MSSFGeometryWarning, match="degrees"):
        head.loss_from_boxes(torch.randn(len(cent)), cent, batch, boxes)


def test_gt_boxes_with_radian_yaw_after_flip_and_rotation_do_not_warn():
    cent, batch = _centroids()
    # yaw in [-pi, pi], flipped (pi - yaw) and rotated by pi/4: up to 2.25 pi
    yaws = torch.tensor([-math.pi, 0.3, math.pi - (-math.pi) + math.pi / 4, -2.25 * math.pi])
    boxes = torch.tensor([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0]]).repeat(4, 1)
    boxes[:, 6] = yaws
    with _no_mssf_warning():
        labels, _ = voxel_foreground_labels(cent, batch, [boxes, boxes])
        points_in_boxes(cent, boxes)
    # same labels as per-box calls (the refactor kept the computation)
    b0 = batch == 0
    assert torch.equal(labels[b0].bool(), points_in_boxes(cent[b0], boxes).any(1))


# --- the head's scores passed as logits ----------------------------------------------------------------------
def _head_outputs(n=200):
    torch.manual_seed(0)
    head = SemanticGuidedHead(16)
    coords = torch.stack([torch.zeros(n), torch.zeros(n), torch.arange(n) // 20, torch.arange(n) % 20], 1).int()
    vox = SparseVoxels(torch.randn(n, 16), coords, (1, 20, 20), 1, voxel_size=(0.2, 0.2, 0.2), point_range_min=(0.0, 0.0, 0.0))
    _, scores, logits = head(vox, return_logits=True)
    return head, scores, logits, (torch.rand(n) > 0.5).float()


def test_head_loss_of_scores_instead_of_logits_warns():
    head, scores, logits, labels = _head_outputs()
    with pytest.warns(MSSFGeometryWarning, match=r"logits: all 200 values lie in .* sigmoid scores passed as logits"):
        head.loss(scores, labels)
    with _no_mssf_warning():
        head.loss(logits, labels)
        head.loss(scores[:31], labels[:31])  # too few for a verdict
        set_geometry_checks(False)
        head.loss(scores, labels)


# --- QueryInit's point_cloud_range against the block's grid -------------------------------------------------
spconv = pytest.importorskip("spconv.pytorch")


def _block(pcr):
    down = spconv.SparseSequential(spconv.SparseConv3d(16, 32, 3, stride=2, padding=1, bias=False),
                                   nn.BatchNorm1d(32), nn.ReLU())
    return FusionBlock(MSDFF(embed_dim=32, value_channels=64, num_heads=8, num_levels=2, num_points=2),
                       downsample=down, query_init=QueryInit(32, 64, 32, point_cloud_range=pcr),
                       grid=VoxelGrid((0.05, 0.05, 0.125), PC_MIN + (51.2, 25.6, 2.0)))


def _stage_inputs(shape):
    xyz, batch = _cloud()
    cells = ((xyz - torch.tensor(PC_MIN)) / torch.tensor([0.05, 0.05, 0.125])).floor()
    coords = torch.unique(torch.cat([batch[:, None].float(), cells.flip(1)], 1), dim=0).int()
    x = spconv.SparseConvTensor(torch.randn(len(coords), 16), coords, shape, 2)
    h, w = 128, 256
    k = torch.tensor([[100.0, 0, w / 2], [0, 100, h / 2], [0, 0, 1]])
    l2i = (k @ torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])).expand(2, 1, 3, 4)
    inputs = FusionInputs([torch.randn(2, 64, h // s, w // s) for s in (4, 8)], l2i, (h, w), xyz, batch)
    return x, inputs


def test_query_init_range_of_another_grid_warns_once():
    x, inputs = _stage_inputs([40, 1024, 1024])
    block = _block((0.0, -40.0, -3.0, 70.4, 40.0, 1.0))  # KITTI's range beside a VoD grid
    with pytest.warns(MSSFGeometryWarning, match=r"point_cloud_range: expected the block's grid, about "
                                                 r"\(0\.0, -25\.6, -3\.0, 51\.2, 25\.6, 2\.0\).*got \(0\.0, -40\.0"):
        block(x, inputs)
    with _no_mssf_warning():  # once per block, not every step
        block(x, inputs)


def test_query_init_range_of_the_grid_passes_padded_shapes():
    with _no_mssf_warning():
        _block(PC_MIN + PC_MAX)(*_stage_inputs([40, 1024, 1024]))
        _block(PC_MIN + PC_MAX)(*_stage_inputs([41, 1024, 1024]))  # OpenPCDet's extra z cell


# --- a channels-last BEV map / image level against a channels-first module ------------------------------------
def test_channels_last_maps_name_the_permute():
    from mssf_blocks import SFF, PillarLift, VoxelCentroidProjector

    xyz, batch = _cloud()
    vox = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    lift = PillarLift(channels=16, num_z=vox.spatial_shape[0])
    hb, wb = lift.bev_shape(vox)
    bev = torch.randn(2, 16, hb, wb)
    with pytest.raises(MSSFError, match=r"bev: expected 16 channels.*channels-last.*bev\.permute\(0, 3, 1, 2\)"):
        lift(bev.permute(0, 2, 3, 1), vox)
    h, w = 64, 96
    l2i = (torch.tensor([[50.0, 0, w / 2], [0, 50, h / 2], [0, 0, 1]])
           @ torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])).expand(2, 1, 3, 4)
    proj = VoxelCentroidProjector()(vox, xyz, batch, l2i, (h, w))
    levels = [torch.randn(2, 32, h // s, w // s) for s in (4, 8)]
    with pytest.raises(MSSFError, match=r"image_features\[0\].*channels-last.*permute\(0, 3, 1, 2\)"):
        SFF([32, 32], 16)([lv.permute(0, 2, 3, 1) for lv in levels], proj)
    with pytest.raises(MSSFError, match="build it with in_channels") as err:  # a plain width error: no hint
        SFF([40, 32], 16)(levels, proj)
    assert "channels-last" not in str(err.value)


# --- lidar2img / points_to_sensor on another device than the points -------------------------------------------
def test_matrices_on_another_device_are_named():
    from mssf_blocks import VoxelCentroidProjector

    xyz, batch = _cloud()
    vox = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), PC_MIN, PC_MAX)
    l2i = torch.tensor([[50.0, 0, 48], [0, 50, 32], [0, 0, 1]]) @ torch.tensor(
        [[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])
    l2i = l2i.expand(2, 1, 3, 4)
    proj = VoxelCentroidProjector()
    # (a "meta" tensor stands for a CUDA one beside CPU points: the same device comparison)
    with pytest.raises(MSSFError, match=r"lidar2img: expected device cpu \(of points\), got meta"):
        proj(vox, xyz, batch, l2i.to("meta"), (64, 96))
    with pytest.raises(MSSFError, match=r"points_to_sensor: expected device cpu \(of points\), got meta"):
        proj(vox, xyz, batch, l2i, (64, 96), torch.eye(4).expand(2, 4, 4).to("meta"))


# --- image_size of a feature level (feats[0].shape[-2:]) instead of the image ---------------------------------
def _frustum_scene(n=400, h=320, w=512, f=200.0, seed=0):
    """Points spread over the whole image (back-projected from uniform pixels at 5-10 m) for a camera looking
    along +x, two samples, and their voxels."""
    g = torch.Generator().manual_seed(seed)
    u, v = torch.rand(2 * n, generator=g) * w, torch.rand(2 * n, generator=g) * h
    d = 5 + 5 * torch.rand(2 * n, generator=g)
    xyz = torch.stack([d, -(u - w / 2) * d / f, -(v - h / 2) * d / f], 1)
    batch = torch.arange(2).repeat_interleave(n)
    vox = voxelize_points(xyz, batch, 2, (0.4, 0.4, 0.4), (0.0, -12.8, -8.0), (12.8, 12.8, 8.0))
    k = torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]])
    l2i = (k @ torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])).expand(2, 1, 3, 4)
    return xyz, batch, vox, l2i


def test_image_size_of_a_feature_level_warns():
    from mssf_blocks import VoxelCentroidProjector

    xyz, batch, vox, l2i = _frustum_scene()
    with pytest.warns(MSSFGeometryWarning, match=r"inside 4 x it.*principal point lands at \(2\.0, 2\.0\).*"
                                                 r"is image_size smaller than the image lidar2img projects into"):
        VoxelCentroidProjector()(vox, xyz, batch, l2i, (80, 128))  # level 0 at stride 4 of (320, 512)
    with pytest.warns(MSSFGeometryWarning, match=r"inside 8 x it"):
        VoxelCentroidProjector()(vox, xyz, batch, l2i, (40, 64))
    with _no_mssf_warning():  # the right size
        VoxelCentroidProjector()(vox, xyz, batch, l2i, (320, 512))


# --- gt boxes in the camera frame (KITTI label files) for the semantic head's labels ---------------------------
def test_gt_boxes_in_the_camera_frame_warn():
    cent, batch = _centroids()  # sensor frame: x 5-30 m ahead, z -2.5..0.5 m
    # the same cars in the sensor frame and as KITTI camera-frame labels (x = -y, y = -z + h/2, z = x)
    sensor = torch.tensor([[12.0, 1.0, -1.0, 4.0, 1.8, 1.5, 0.2], [20.0, -2.0, -1.2, 4.2, 1.9, 1.6, -0.1]])
    camera = torch.stack([-sensor[:, 1], -sensor[:, 2] + sensor[:, 5] / 2, sensor[:, 0], sensor[:, 3],
                          sensor[:, 5], sensor[:, 4], sensor[:, 6]], 1)
    with pytest.warns(MSSFGeometryWarning, match=r"gt_boxes\[0\]: every box lies .* camera frame"):
        voxel_foreground_labels(cent, batch, [camera, camera])
    with _no_mssf_warning():
        voxel_foreground_labels(cent, batch, [sensor, sensor])
        voxel_foreground_labels(cent, batch, [camera, sensor])  # one sample right: no verdict
        voxel_foreground_labels(cent[:15], batch[:15], [camera, camera])  # fewer than 16 voxels: no verdict
