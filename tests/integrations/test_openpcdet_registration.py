"""The documented registration lines in OpenPCDet's ``__init__.py`` files, and the fixture's stand-ins.

A second copy of the archive gets the lines of docs/frameworks.md ("Register the MSSF classes")
appended to its three ``__init__.py`` files; a fresh interpreter then imports pcdet and finds the MSSF
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
import mssf_examples.openpcdet.vod_dataset as v, mssf_examples.openpcdet.detectors as det
assert d.__all__['VoDDataset'] is v.VoDDataset
assert {'MSSFVoxelBackBone8x', 'MSSFVoxelResBackBone8x', 'MSSFVoxelResBackBone8xVoxelNeXt'} <= set(b.__all__)
assert m.__all__['MSSFVoxelNeXt'] is det.MSSFVoxelNeXt and m.__all__['MSSFSECONDNet'] is det.MSSFSECONDNet
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
    assert sorted(edits) == ["pcdet/datasets/__init__.py", "pcdet/models/backbones_3d/__init__.py",
                             "pcdet/models/detectors/__init__.py"]
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
