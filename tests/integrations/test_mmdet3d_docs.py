"""The ``python -m mssf_examples.mmdet3d`` commands of docs/frameworks.md ("mmdetection3d"), run in order.

In a temporary folder laid out as the docs assume (``data/view_of_delft`` a generated VoD release tree with
``.jpg`` images, ``examples`` the repository's), each command line of the section's ``bash`` blocks that
starts with ``python -m mssf_examples.mmdet3d`` runs in-process through the entry's ``main``. Changed
from the printed text, and only this: ``train`` gets 1 epoch (2 with ``--resume``), batch 1, no
workers and a 160 x 100 image (``--image-scale`` / ``--cfg-options``), and ``test`` the checkpoint that
short run wrote (``epoch_1.pth`` for the printed ``epoch_80.pth``).
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import require_mmdet3d, write_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[2]
SMALL = ["--image-scale", "160", "100", "--cfg-options", "train_dataloader.batch_size=1",
         "train_dataloader.num_workers=0", "train_dataloader.persistent_workers=False",
         "val_dataloader.num_workers=0", "val_dataloader.persistent_workers=False",
         "test_dataloader.num_workers=0", "test_dataloader.persistent_workers=False"]


def doc_commands():
    text = (REPO / "docs" / "frameworks.md").read_text()
    section = text[text.index("## mmdetection3d"):text.index("## Conventions that differ")]
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", section, re.S):
        lines += [ln.strip() for ln in block.replace("\\\n", " ").splitlines()
                  if ln.strip().startswith("python -m mssf_examples.mmdet3d")]
    return lines


def test_docs_commands_run_as_printed(tmp_path, monkeypatch):
    require_mmdet3d()
    from mssf_examples.mmdet3d.cli import main

    commands = doc_commands()
    assert [shlex.split(c)[3] for c in commands] == ["infos", "train", "test", "train"], commands
    write_tree(tmp_path / "data" / "view_of_delft")
    (tmp_path / "data" / "view_of_delft" / "radar_5frames" / "vod_infos_train.pkl").unlink()  # the docs write it
    (tmp_path / "examples").symlink_to(REPO / "examples")
    monkeypatch.chdir(tmp_path)
    # the entry's `test` / `--resume` set this for the rest of the process (mmengine 0.10.7 checkpoints):
    # set it through monkeypatch so that it is gone again after this test
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    for cmd in commands:
        argv = shlex.split(cmd)[3:]
        if argv[0] == "train":
            epochs = 2 if "--resume" in argv else 1
            argv += SMALL + [f"train_cfg.max_epochs={epochs}", f"param_scheduler.0.end={epochs}"]
        elif argv[0] == "test":
            argv = [a.replace("epoch_80.pth", "epoch_1.pth") for a in argv] + SMALL
        assert main(argv) == 0, cmd
    work = tmp_path / "work_dirs" / "mssf_pointpillars_vod"
    assert (tmp_path / "data" / "view_of_delft" / "radar_5frames" / "vod_infos_train.pkl").is_file()
    assert (work / "epoch_1.pth").is_file() and (work / "epoch_2.pth").is_file()  # resumed at epoch 1
    logs = "".join(p.read_text() for p in work.glob("*/*.log"))
    assert "resumed" in logs.lower() and "VoD/driving_corridor/mAP/AP3D_R11" in logs
