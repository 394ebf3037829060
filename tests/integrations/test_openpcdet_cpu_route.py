"""docs/frameworks.md's OpenPCDet route without CUDA (``--cpu``), run as printed in fresh processes.

OpenPCDet is unpacked as a user's clone is before ``setup.py`` (no ``pcdet/version.py``, none of the seven
compiled extension modules) and is NOT on the path; this machine has no CUDA and no ``torchvision``. The
``--cpu`` lines of the section's ``bash`` blocks run from its ``tools/`` with only the project on
``PYTHONPATH``, each with CPU sizes appended as OpenPCDet's own ``--set`` options. The processes start through
``python -c`` only to make ``time.sleep`` a no-op (``train.py``'s evaluation waits 30 s for further
checkpoints); the module then runs as ``python -m mssf_examples.openpcdet``.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest

pytest.importorskip("spconv")

REPO = Path(__file__).resolve().parents[2]
ARCHIVE = REPO.parent / "shared" / "thirdparty" / "openpcdet-8caccce.tar.gz"  # as the openpcdet fixture
PREFIX = "OpenPCDet-8caccce"
ENTRY = "python -m mssf_examples.openpcdet --cpu "
SIZES = ["--set", "MODEL.IMAGE_BRANCH.DEPTH", "18", "MODEL.IMAGE_BRANCH.BASE_CHANNELS", "8", "OPTIMIZATION.PCT_START", "0.5"]
RUNNER = ("import runpy, sys, time; time.sleep = lambda seconds: None; sys.argv = ['mssf_examples.openpcdet'] + sys.argv[1:]; "
          "runpy.run_module('mssf_examples.openpcdet', run_name='__main__', alter_sys=True)")


def documented_cpu_commands():
    """The ``python -m mssf_examples.openpcdet --cpu`` lines of the OpenPCDet section, continuations joined."""
    text = (REPO / "docs" / "frameworks.md").read_text()
    section = text.split("## OpenPCDet", 1)[1].split("\n## ", 1)[0]
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", section, flags=re.S):
        for line in block.replace("\\\n", " ").splitlines():
            line = " ".join(line.split("#", 1)[0].split())
            if line.startswith(ENTRY):
                lines.append(line)
    return lines


def test_the_documented_cpu_route_runs_on_an_unbuilt_clone(openpcdet, tmp_path):
    """(``openpcdet``: skips, or fails under CI=true, where the archive or OpenPCDet's imports are missing.)"""
    commands = documented_cpu_commands()
    assert [c.split()[4] for c in commands] == ["create_vod_infos", "train.py", "test.py"], commands
    with tarfile.open(ARCHIVE) as tar:
        tar.extractall(tmp_path, filter="data")
    root = tmp_path / PREFIX
    built = [p for p in (root / "pcdet").rglob("*") if p.suffix in (".so", ".pyd") or p.name == "version.py"]
    assert not built, built
    tools = root / "tools"
    configs = REPO / "examples" / "configs" / "openpcdet"
    shutil.copytree(configs / "dataset_configs", tools / "cfgs" / "dataset_configs", dirs_exist_ok=True)  # step 2
    shutil.copytree(configs / "vod_models", tools / "cfgs" / "vod_models", dirs_exist_ok=True)

    sys.path.insert(0, str(REPO / "examples"))
    import torch

    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import generate_scene, scene_seed

    splits = {s: [generate_scene(scene_seed(0, s, i)) for i in range(n)] for s, n in (("train", 4), ("val", 2))}
    write_vod_tree(root / "data" / "view_of_delft", splits, sensor="radar_5frames", image_format="jpg")  # step 4
    (root / "checkpoints").mkdir()
    torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=256, num_outs=4).state_dict(),
               root / "checkpoints" / "htc_r50_fpn_image_branch.pth")  # the config's CHECKPOINT

    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "CUDA_VISIBLE_DEVICES")}
    env.update(PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples")]), OMP_NUM_THREADS="1")
    probe = "import importlib.util as u, torch; print(u.find_spec('pcdet'), u.find_spec('torchvision'), torch.cuda.is_available())"
    assert subprocess.run([sys.executable, "-c", probe], cwd=tools, env=env, capture_output=True, text=True,
                          check=True).stdout.split() == ["None", "None", "False"]
    for command in commands:
        args = shlex.split(command)[3:]  # after "python -m mssf_examples.openpcdet"
        if args[1] != "create_vod_infos":
            args += SIZES
        done = subprocess.run([sys.executable, "-c", RUNNER, *args], cwd=tools, env=env, capture_output=True,
                              text=True, timeout=900)
        assert done.returncode == 0, (command, done.stdout[-3000:], done.stderr[-3000:])
    out = root / "output" / "vod_models" / "mssf_voxelnext" / "default"
    assert (out / "ckpt" / "checkpoint_epoch_1.pth").is_file()
    logs = list((out / "eval").rglob("log_eval_*.txt"))
    assert logs and "VoD driving_corridor:" in logs[-1].read_text() and "mAP3D R40" in logs[-1].read_text()
