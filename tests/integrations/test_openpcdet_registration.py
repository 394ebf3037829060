"""The documented registration lines in OpenPCDet's ``__init__.py`` files, and the fixture's stand-ins.

A second copy of the archive gets the lines of docs/frameworks.md ("Register the MSSF classes")
appended to its four ``__init__.py`` files; a fresh interpreter then imports pcdet and finds the MSSF
names in the registries, with nothing else registered by hand.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

CHECK = """
import pcdet.datasets as d, pcdet.models.backbones_3d as b, pcdet.models.detectors as m
import pcdet.models.backbones_2d as b2, mssf_examples.openpcdet.bev_backbone as bev
import mssf_examples.openpcdet.vod_dataset as v, mssf_examples.openpcdet.detectors as det
assert d.__all__['VoDDataset'] is v.VoDDataset
import mssf_examples.openpcdet.tj4d_dataset as t
assert d.__all__['TJ4DDataset'] is t.TJ4DDataset and m.__all__['MSSFCenterPoint'] is det.MSSFCenterPoint
assert {'MSSFVoxelBackBone8x', 'MSSFVoxelResBackBone8x', 'MSSFVoxelResBackBone8xVoxelNeXt'} <= set(b.__all__)
assert m.__all__['MSSFVoxelNeXt'] is det.MSSFVoxelNeXt and m.__all__['MSSFSECONDNet'] is det.MSSFSECONDNet
assert m.__all__['MSSFPointPillar'] is det.MSSFPointPillar and b2.__all__['MSSFBaseBEVBackbone'] is bev.MSSFBaseBEVBackbone
import mssf_examples.openpcdet.voxelnext2d_backbone as vn2d
assert b.__all__['MSSFVoxelResBackBone8xVoxelNeXt2D'] is vn2d.MSSFVoxelResBackBone8xVoxelNeXt2D
print('ok')
"""


def documented_lines():
    """``{init file: lines}`` from the ```text block of docs/frameworks.md that edits pcdet."""
    text = (REPO / "docs" / "frameworks.md").read_text()
    block = re.search(r"```text\n(# pcdet/datasets/__init__.py\n.*?)```", text, re.S).group(1)
    out, current = {}, None
    for line in block.splitlines():
        if line.startswith("# pcdet/"):
            current = line[2:].strip()
            out[current] = []
        elif line.strip():
            out[current].append(line)
    return out


def test_documented_init_lines_register_the_classes(openpcdet_copy, tmp_path):
    root = openpcdet_copy
    edits = documented_lines()
    assert sorted(edits) == ["pcdet/datasets/__init__.py", "pcdet/models/backbones_2d/__init__.py",
                             "pcdet/models/backbones_3d/__init__.py", "pcdet/models/detectors/__init__.py"]
    for name, lines in edits.items():
        with open(root / name, "a") as f:
            f.write("\n" + "\n".join(lines) + "\n")
    # pcdet's data_processor imports torchvision at module level (the registry's builds do not load with
    # the CPU torch); registering needs none of it
    stub = tmp_path / "stubs" / "torchvision"
    stub.mkdir(parents=True)
    (stub / "__init__.py").write_text("transforms = None\n")
    path = [str(root), str(REPO / "src"), str(REPO / "examples"), str(tmp_path / "stubs")]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(path), OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", CHECK], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), out.stderr[-3000:]


def test_stand_ins_raise_when_used(openpcdet):
    from pcdet.ops.iou3d_nms import iou3d_nms_cuda
    from pcdet.ops.roiaware_pool3d import roiaware_pool3d_utils

    with pytest.raises(RuntimeError, match="iou3d_nms_cuda.nms_gpu: OpenPCDet's compiled extension is not built"):
        iou3d_nms_cuda.nms_gpu
    with pytest.raises(RuntimeError, match="roiaware_pool3d_cuda.points_in_boxes_cpu"):
        roiaware_pool3d_utils.points_in_boxes_cpu(__import__("torch").zeros(1, 3), __import__("torch").zeros(1, 7))


def test_an_mmengine_runner_environment_report_works_after_openpcdet(openpcdet):
    """The session's torchvision stand-in (where torchvision does not import) must not break mmdet3d runner tests
    that run after this fixture: mmengine's Runner reports the environment, torchvision's version included."""
    mmengine = pytest.importorskip("mmengine.utils.dl_utils")
    env = mmengine.collect_env()
    assert "TorchVision" in env


def test_voxelnext_wrapper_has_openpcdets_layout(openpcdet):
    """MSSFVoxelResBackBone8xVoxelNeXt (radar only, OpenPCDet's widths) against OpenPCDet's own
    VoxelResBackBone8xVoxelNeXt on the same voxels: the same sparse shape, the same active sites of every
    stage and of the encoded BEV tensor, the same channels and strides."""
    import numpy as np
    import torch
    from easydict import EasyDict
    from pcdet.models.backbones_3d.spconv_backbone_voxelnext import VoxelResBackBone8xVoxelNeXt

    from mssf_blocks.integrations.openpcdet_backbones import MSSFVoxelResBackBone8xVoxelNeXt

    pcr, vs = np.array([0, -25.6, -3, 51.2, 25.6, 2], dtype=np.float32), [0.4, 0.4, 0.125]
    grid = np.round((pcr[3:] - pcr[:3]) / np.array(vs)).astype(np.int64)
    theirs = VoxelResBackBone8xVoxelNeXt(EasyDict(CHANNELS=[16, 32, 64, 128, 128], OUT_CHANNEL=128), 7, grid)
    ours = MSSFVoxelResBackBone8xVoxelNeXt(EasyDict(NAME="MSSFVoxelResBackBone8xVoxelNeXt", NUM_FUSION_BLOCKS=0,
                                                    CHANNELS=[16, 16, 32, 64, 128, 128, 128], OUT_CHANNELS=128),
                                           7, grid, voxel_size=vs, point_cloud_range=pcr)
    assert ours.sparse_shape == list(theirs.sparse_shape)
    assert ours.backbone_channels == theirs.backbone_channels and ours.num_point_features == theirs.num_point_features
    gen = np.random.default_rng(0)
    coords = np.unique(np.concatenate([np.stack([np.full(n, b), gen.integers(0, grid[2], n), gen.integers(0, grid[1], n),
                                                 gen.integers(0, grid[0], n)], 1) for b, n in ((0, 300), (1, 200))]), axis=0)
    batch = lambda: {"voxel_features": torch.randn(len(coords), 7, generator=torch.Generator().manual_seed(0)),  # noqa: E731
                     "voxel_coords": torch.from_numpy(coords).float(), "batch_size": 2}
    a, b = theirs(batch()), ours(batch())

    def sites(t):
        return sorted(map(tuple, t.indices.tolist()))

    # (OpenPCDet's forward overwrites its x_conv4 in place with the stage 4-6 merge: compared via the BEV)
    for key in ("x_conv1", "x_conv2", "x_conv3"):
        ta, tb = a["multi_scale_3d_features"][key], b["multi_scale_3d_features"][key]
        assert list(ta.spatial_shape) == list(tb.spatial_shape) and sites(ta) == sites(tb), key
    ea, eb = a["encoded_spconv_tensor"], b["encoded_spconv_tensor"]
    assert list(ea.spatial_shape) == list(eb.spatial_shape) and sites(ea) == sites(eb)
    assert eb.features.shape == ea.features.shape and b["encoded_spconv_tensor_stride"] == a["encoded_spconv_tensor_stride"]
