"""Cases for the Common-mistakes rows of the independent pass (tests/checks/test_more_mistakes.py): each makes the
mistake with that file's scenes and returns what the library did (tests/helpers/mistakes_registry.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from mistakes_registry import case, outcome

TESTS = Path(__file__).resolve().parents[1] / "checks"


def _more():
    if str(TESTS) not in sys.path:
        sys.path.append(str(TESTS))
    pytest.importorskip("spconv.pytorch")  # test_more_mistakes imports it at module level
    import test_more_mistakes as mm

    return mm


@case("OpenPCDet's `(b, x, y, z, ...)` points into `voxelize_points`")
def _():
    mm = _more()
    from mssf_blocks.functional.geometry import voxel_centroids
    from mssf_blocks.functional.lift import voxelize_points

    xyz, batch = mm._cloud()
    pts = torch.cat([batch[:, None].float(), xyz], 1)
    vox = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), mm.PC_MIN, mm.PC_MAX)
    return outcome(lambda: voxelize_points(pts, batch, 2, (0.16, 0.16, 0.5), mm.PC_MIN, mm.PC_MAX),
                   lambda: voxel_centroids(pts, batch, vox.coords, vox.spatial_shape, 2, vox.voxel_size,
                                           vox.point_range_min))


@case("box yaw in degrees")
def _():
    mm = _more()
    from mssf_blocks.functional.heads import points_in_boxes, voxel_foreground_labels

    cent, batch = mm._centroids()
    boxes = [torch.tensor([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 90.0]]), torch.zeros(0, 7)]
    return outcome(lambda: voxel_foreground_labels(cent, batch, boxes), lambda: points_in_boxes(cent, boxes[0]))


@case("the head's `scores` (after the sigmoid) passed to `head.loss` as logits")
def _():
    head, scores, _, labels = _more()._head_outputs()
    return outcome(lambda: head.loss(scores, labels))


@case("`QueryInit(point_cloud_range=...)` of another grid")
def _():
    mm = _more()
    x, inputs = mm._stage_inputs([40, 1024, 1024])
    block = mm._block((0.0, -40.0, -3.0, 70.4, 40.0, 1.0))
    return outcome(lambda: block(x, inputs))


@case("a channels-last BEV map into `PillarLift`")
def _():
    mm = _more()
    from mssf_blocks import PillarLift
    from mssf_blocks.functional.lift import voxelize_points

    xyz, batch = mm._cloud()
    vox = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), mm.PC_MIN, mm.PC_MAX)
    lift = PillarLift(channels=16, num_z=vox.spatial_shape[0])
    hb, wb = lift.bev_shape(vox)
    return outcome(lambda: lift(torch.randn(2, hb, wb, 16), vox))


@case("`lidar2img` / `points_to_sensor` / `points_batch` on another device than the points")
def _():
    mm = _more()
    from mssf_blocks import VoxelCentroidProjector
    from mssf_blocks.functional.lift import voxelize_points

    xyz, batch = mm._cloud()
    vox = voxelize_points(xyz, batch, 2, (0.16, 0.16, 0.5), mm.PC_MIN, mm.PC_MAX)
    l2i = (torch.tensor([[50.0, 0, 48], [0, 50, 32], [0, 0, 1]])
           @ torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])).expand(2, 1, 3, 4)
    # a "meta" tensor stands for a CUDA one beside CPU points (the same device comparison)
    return outcome(lambda: VoxelCentroidProjector()(vox, xyz, batch, l2i.to("meta"), (64, 96)))


@case("`image_size` of a feature level")
def _():
    mm = _more()
    from mssf_blocks import VoxelCentroidProjector

    xyz, batch, vox, l2i = mm._frustum_scene()
    return outcome(lambda: VoxelCentroidProjector()(vox, xyz, batch, l2i, (80, 128)))


@case("gt boxes in the camera frame")
def _():
    mm = _more()
    from mssf_blocks.functional.heads import voxel_foreground_labels

    cent, batch = mm._centroids()
    sensor = torch.tensor([[12.0, 1.0, -1.0, 4.0, 1.8, 1.5, 0.2], [20.0, -2.0, -1.2, 4.2, 1.9, 1.6, -0.1]])
    camera = torch.stack([-sensor[:, 1], -sensor[:, 2] + sensor[:, 5] / 2, sensor[:, 0], sensor[:, 3],
                          sensor[:, 5], sensor[:, 4], sensor[:, 6]], 1)
    return outcome(lambda: voxel_foreground_labels(cent, batch, [camera, camera]))
