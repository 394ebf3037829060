"""``mssf_examples.data.kitti_export``'s View-of-Delft tree and prediction files, read back with ``mssf_examples.data.kitti_io``.

The tree holds generated scenes (``generated_tree.py``); the real VoD label lines (skipped without
``../shared/realdata``) are written again from their boxes. The CLI on the same tree: ``test_cli.py``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_examples.data.kitti_export import kitti_lines, scene_calibration, write_kitti_file  # noqa: E402
from mssf_examples.data.kitti_io import (  # noqa: E402
    VOD_CLASSES,
    VOD_RADAR,
    Calibration,
    KittiFormatDataset,
    camera_boxes_to_sensor,
    parse_labels,
    read_calibration,
)

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from generated_tree import SIZE, write_generated_tree  # noqa: E402


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_generated_tree(tmp_path_factory.mktemp("vod"))


# ---------------------------------------------------------------------------------------------------
# (1) the written tree reads back as the scenes
# ---------------------------------------------------------------------------------------------------
def test_tree_reads_back_as_the_scenes(tree):
    root, ids, scenes = tree
    assert ids == {"train": ["00000", "00001", "00002", "00003"], "val": ["00004", "00005"]}
    for split in ("train", "val"):
        ds = KittiFormatDataset(root, VOD_RADAR, sensor="radar_5frames", split=split)
        assert ds.layout == "nested" and ds.frame_ids == ids[split]
        for frame, scene in zip(ds, scenes[split]):
            assert torch.equal(frame.points, scene.points)
            assert frame.raw_points.shape[1] == 7
            torch.testing.assert_close(frame.lidar2img, scene.lidar2img, rtol=0, atol=1e-5)
            assert frame.image_size == SIZE
            # 8-bit PNG: within half a quantisation step
            assert (frame.image.double() / 255 - scene.image.double()).abs().max() <= 0.5 / 255 + 1e-6
            g = scene.gt_boxes.double()
            assert torch.equal(frame.gt_labels, scene.gt_labels)
            assert frame.gt_boxes.shape == g.shape
            torch.testing.assert_close(frame.gt_boxes[:, :6], g[:, :6], rtol=0, atol=1e-5)
            assert wrap(frame.gt_boxes[:, 6] - g[:, 6]).abs().max() < 1e-5
            # clutter lines are written as another VoD type and are not evaluated
            others = [n for n, lab in zip(frame.objects.names, frame.labels.tolist()) if lab < 0]
            assert others == ["bicycle_rack"] * len(scene.clutter_boxes)


def test_tree_calibration_files(tree):
    root, ids, scenes = tree
    calib = read_calibration(root / "radar_5frames" / "training" / "calib" / "00004.txt")
    s = scenes["val"][0]
    np.testing.assert_allclose(calib.P2[:, :3].numpy(), s.intrinsics.numpy(), rtol=0, atol=1e-12)
    assert calib.P2[:, 3].abs().max() == 0
    np.testing.assert_allclose(calib.Tr_velo_to_cam.numpy(), s.sensor_to_camera[:3].numpy(), rtol=0, atol=1e-12)
    assert torch.equal(calib.R0_rect, torch.eye(3, dtype=torch.float64))


# ---------------------------------------------------------------------------------------------------
# (2) prediction files: parse back with the reader, compare with the boxes; 2D box by hand
# ---------------------------------------------------------------------------------------------------
def _tilted_calib() -> Calibration:
    """Camera pitched down by 6 degrees and yawed by 2, like VoD's radar extrinsics; KITTI-like P2."""
    def rot(axis, deg):
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        m = np.eye(3)
        i, j = [(1, 2), (0, 2), (0, 1)][axis]
        m[i, i], m[i, j], m[j, i], m[j, j] = c, -s, s, c
        return m

    perm = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    r = rot(0, 6.0) @ rot(1, 2.0) @ perm
    tr = np.concatenate([r, np.array([[0.05], [0.9], [1.4]])], 1)
    p2 = np.array([[700.0, 0.0, 600.0, 45.0], [0.0, 700.0, 180.0, -0.3], [0.0, 0.0, 1.0, 0.005]])
    return Calibration(P2=torch.tensor(p2), R0_rect=torch.tensor(rot(1, 0.5)), Tr_velo_to_cam=torch.tensor(tr))


def _hand_corners_cam(loc, hwl, ry):
    """KITTI label box corners in the camera frame (numpy, from the label definition)."""
    h, w, l = hwl
    out = []
    for sx in (1, -1):
        for sz in (1, -1):
            for y in (0.0, -h):
                x, z = sx * l / 2, sz * w / 2
                out.append([math.cos(ry) * x + math.sin(ry) * z + loc[0], y + loc[1],
                            -math.sin(ry) * x + math.cos(ry) * z + loc[2]])
    return np.array(out)


@pytest.mark.parametrize("calib_kind", ["scene", "tilted"])
def test_prediction_file_round_trip(tree, tmp_path, calib_kind):
    root, ids, scenes = tree
    calib = scene_calibration(scenes["val"][0]) if calib_kind == "scene" else _tilted_calib()
    size = SIZE if calib_kind == "scene" else (375, 1242)
    g = torch.Generator().manual_seed(1)
    k = 7
    boxes = torch.cat([torch.rand(k, 1, generator=g, dtype=torch.float64) * 30 + 4,
                       (torch.rand(k, 1, generator=g, dtype=torch.float64) - 0.5) * 16,
                       torch.rand(k, 1, generator=g, dtype=torch.float64) * 2 - 1.5,
                       torch.rand(k, 3, generator=g, dtype=torch.float64) * 3 + 0.4,
                       (torch.rand(k, 1, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi], 1)
    labels = torch.tensor([0, 1, 2, 0, 1, 2, 0])
    scores = torch.rand(k, generator=g, dtype=torch.float64)
    path = write_kitti_file(tmp_path / "00042.txt", kitti_lines(boxes, labels, VOD_CLASSES, calib, size, scores=scores))
    text = path.read_text()
    assert text.endswith("\n") and all(len(line.split()) == 16 for line in text.splitlines())
    obj = parse_labels(text)
    assert obj.names == [VOD_CLASSES[i] for i in labels.tolist()]
    assert obj.truncation.eq(-1).all() and obj.occlusion.eq(-1).all()
    torch.testing.assert_close(obj.score, scores, rtol=0, atol=1e-6)
    back = camera_boxes_to_sensor(obj.location, obj.dimensions, obj.rotation_y, calib)
    torch.testing.assert_close(back[:, :6], boxes[:, :6], rtol=0, atol=1e-5)
    assert wrap(back[:, 6] - boxes[:, 6]).abs().max() < 1e-5
    # dims h w l = dz dy dx
    torch.testing.assert_close(obj.dimensions, boxes[:, [5, 4, 3]], rtol=0, atol=1e-6)
    p2 = calib.P2.numpy()
    r0 = np.eye(4)
    r0[:3, :3] = calib.R0_rect.numpy()
    h_img, w_img = size
    for i in range(k):
        loc, hwl, ry = obj.location[i].numpy(), obj.dimensions[i].numpy(), float(obj.rotation_y[i])
        # alpha = ry - atan2(x, z) of the box centre (camera frame)
        expect_alpha = wrap(torch.tensor(ry - math.atan2(loc[0], loc[2]))).item()
        assert abs(wrap(torch.tensor(float(obj.alpha[i]) - expect_alpha)).item()) < 1e-5
        corners = _hand_corners_cam(loc, hwl, ry)  # rectified camera frame
        hom = np.concatenate([corners, np.ones((8, 1))], 1) @ p2.T
        if (hom[:, 2] <= 1e-5).any():
            assert obj.boxes_2d[i].abs().max() == 0
            continue
        uv = hom[:, :2] / hom[:, 2:]
        ref = [np.clip(uv[:, 0].min(), 0, w_img - 1), np.clip(uv[:, 1].min(), 0, h_img - 1),
               np.clip(uv[:, 0].max(), 0, w_img - 1), np.clip(uv[:, 1].max(), 0, h_img - 1)]
        np.testing.assert_allclose(obj.boxes_2d[i].numpy(), ref, rtol=0, atol=1e-4)
    # no detections -> an empty file (official kits expect one file per frame)
    empty = write_kitti_file(tmp_path / "00043.txt", kitti_lines(torch.zeros(0, 7), torch.zeros(0, dtype=torch.long),
                                                                  VOD_CLASSES, calib, size, scores=torch.zeros(0)))
    assert empty.read_text() == ""


# ---------------------------------------------------------------------------------------------------
# real VoD frames (skipped without ../shared/realdata): the writer reproduces the released label lines
# ---------------------------------------------------------------------------------------------------
@pytest.mark.realdata
def test_writer_reproduces_vod_label_lines(realdata_root):
    """Label -> sensor box -> kitti_lines gives back the released alpha, 2D box, dims, location, ry."""
    ds = KittiFormatDataset(realdata_root / "vod", VOD_RADAR, sensor="radar", load_image=False)
    assert len(ds) >= 1
    for frame in ds:
        ref = frame.objects
        lines = kitti_lines(frame.boxes, frame.labels, VOD_CLASSES, frame.calib, frame.image_size,
                            scores=torch.ones(len(ref)), names=ref.names)
        got = parse_labels("\n".join(lines))
        assert got.names == ref.names
        torch.testing.assert_close(got.location, ref.location, rtol=0, atol=1e-5)
        torch.testing.assert_close(got.dimensions, ref.dimensions, rtol=0, atol=1e-5)
        assert wrap(got.rotation_y - ref.rotation_y).abs().max() < 1e-5
        assert wrap(got.alpha - ref.alpha).abs().max() < 1e-5  # VoD: alpha = ry - atan2(x, z)
        torch.testing.assert_close(got.boxes_2d, ref.boxes_2d, rtol=0, atol=1e-3)  # files hold 4-5 decimals
