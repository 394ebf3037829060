"""Issue 33, item 4: evaluation and CLI misuse gets one line naming it (exit status 2, no traceback).

The trees are the generated VoD-layout tree (``generated_tree.py``), copied and broken here one way each;
the TJ4D tree is the same frames with 8 stored columns, as in ``test_cli.py``.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.evaluation.metrics import evaluate  # noqa: E402
from mssf_examples.data.kitti_io import parse_labels  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from cli_refusal import refused_line as _fails  # noqa: E402
from generated_tree import write_generated_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    root, ids, _ = write_generated_tree(tmp_path_factory.mktemp("vod"))
    return root, ids


def _copy(root, dst):
    shutil.copytree(root, dst)
    return dst, dst / "radar_5frames" / "training"


def _train(root, out, dataset="vod"):
    return ["train", "--dataset", dataset, "--data-root", str(root), "--preset", "tiny", "--steps", "2",
            "--batch-size", "2", "--threads", "1", "--no-progress", "--workers", "0", "--out", str(out)]




def test_out_an_existing_file(tree, tmp_path, capsys):
    root, _ = tree
    f = tmp_path / "a_file"
    f.write_text("x")
    line = _fails(_train(root, f), capsys)
    assert "--out" in line and "existing file" in line and str(f) in line


def test_vod_tree_as_tj4d_and_tj4d_points_as_vod(tree, tmp_path, capsys):
    root, _ = tree
    line = _fails(_train(root / "radar_5frames", tmp_path / "o", "tj4d"), capsys)
    assert "rows of 7" in line and "--dataset vod" in line
    # TJ4D's 8 columns (x, y, z, V_r, Range, Power, Alpha, Beta) in the VoD layout: named by the file contents
    vod, train = _copy(root, tmp_path / "t")
    for f in (train / "velodyne").iterdir():
        p = np.fromfile(f, dtype="<f4").reshape(-1, 7)
        cols = [p[:, 0], p[:, 1], p[:, 2], p[:, 4], np.linalg.norm(p[:, :3], axis=1), p[:, 3],
                np.arctan2(p[:, 1], p[:, 0]), np.zeros(len(p))]
        np.stack(cols, 1).astype("<f4").tofile(f)
    line = _fails(_train(vod, tmp_path / "o2"), capsys)
    assert "rows of 8" in line and "--dataset tj4d" in line


def test_truncated_point_file(tree, tmp_path, capsys):
    vod, train = _copy(tree[0], tmp_path / "t")
    path = train / "velodyne" / "00001.bin"
    path.write_bytes(path.read_bytes()[:-6])  # half a float
    line = _fails(_train(vod, tmp_path / "o"), capsys)
    assert str(path) in line and "truncated" in line


def test_unknown_class_in_a_label(tree, tmp_path, capsys):
    vod, train = _copy(tree[0], tmp_path / "t")
    for f in sorted((train / "label_2").iterdir()):
        lines = f.read_text().splitlines()
        if lines:
            lines[0] = "Zeppelin " + lines[0].split(" ", 1)[1]
            f.write_text("\n".join(lines) + "\n")
    line = _fails(_train(vod, tmp_path / "o"), capsys)
    assert "unknown object type 'Zeppelin'" in line and "label_2" in line


def test_calib_without_p2(tree, tmp_path, capsys):
    vod, train = _copy(tree[0], tmp_path / "t")
    for f in (train / "calib").iterdir():
        f.write_text("\n".join(line for line in f.read_text().splitlines() if not line.startswith("P2")))
    line = _fails(_train(vod, tmp_path / "o"), capsys)
    assert "P2" in line and "calib" in line


# ---------------------------------------------------------------------------------------------------
# evaluate
# ---------------------------------------------------------------------------------------------------
LABELS = ("Car 0.00 0 0.0 10 10 50 50 1.5 1.6 4.0 2.0 1.5 20.0 0.3 0.9\n"
          "Pedestrian 0.00 0 0.0 60 10 70 50 1.7 0.6 0.8 -3.0 1.6 12.0 -1.0 0.8\n"
          "DontCare -1 -1 -10 0 0 5 5 -1 -1 -1 -1000 -1000 -1000 -10 0.1\n")


def test_exact_protocol_accepts_kitti_objects():
    gt = parse_labels(LABELS)
    perfect = parse_labels(LABELS)
    res = evaluate([perfect], [gt], ["Car", "Pedestrian"], protocol="exact",
                   regions={"entire_area": None})["entire_area"]
    assert res["Car"]["AP3D_R40"] == pytest.approx(100.0) and res["Pedestrian"]["AP3D_R40"] == pytest.approx(100.0)
    # a car moved by its own length: no overlap, AP 0 (the boxes are really compared)
    moved = parse_labels(LABELS.replace(" 2.0 1.5 20.0 ", " 2.0 1.5 24.5 "))
    res = evaluate([moved], [gt], ["Car", "Pedestrian"], protocol="exact", regions={"entire_area": None})
    assert res["entire_area"]["Car"]["AP3D_R40"] == pytest.approx(0.0)


def test_one_based_prediction_labels_are_refused():
    boxes = torch.tensor([[10.0, 0, 0, 4, 2, 1.5, 0], [5.0, 2, 0, 1, 1, 1.7, 0]], dtype=torch.float64)
    gt = {"boxes": boxes, "labels": torch.tensor([0, 1])}
    pred = {"boxes": boxes, "scores": torch.tensor([0.9, 0.8]), "labels": torch.tensor([1, 2])}  # 1-based
    with pytest.raises(MSSFError, match=r"1-based.*labels - 1"):
        evaluate([pred], [gt], ["Car", "Pedestrian"], protocol="exact")
    good = dict(pred, labels=pred["labels"] - 1)
    res = evaluate([good], [gt], ["Car", "Pedestrian"], protocol="exact", regions={"entire_area": None})
    assert res["entire_area"]["mAP"]["AP3D_R40"] == pytest.approx(100.0)
