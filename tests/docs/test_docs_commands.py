"""Every shell command of README.md and docs/*.md runs as printed, or is listed here with the reason it cannot.

The commands (```bash / ```sh / ```shell blocks, ``$ `` lines of ```console blocks; ``doc_commands.py``)
are classified by ``(file, command text)``:

* ``RUN``: run as printed; each doc page's runnable commands run in page order (a later ``eval``
  reads the checkpoint an earlier ``train`` wrote) in one fresh copy of the repository, on generated
  data: only the placeholder paths the docs name as the reader's (``/data/view_of_delft``,
  ``/data/TJ4DRadSet``, the scratch ``/tmp/``) are replaced by generated trees (``doc_commands.PLACEHOLDERS``);
* ``SHORTENED``: a training run of hours runs with its length options replaced (each replaced text must
  still be in the command), everything else as printed;
* ``NOT_RUN``: cannot run here, with the reason (a GPU, several nodes, a registry install, a run of
  minutes that another test runs at a smaller size); a whole page or block can be marked instead, by
  ``NOT_RUN_FILES`` or by an HTML comment ``<!-- commands: not run: REASON -->`` right before its fence.

A command in none of these (a new one, or an old one whose text changed) fails
``test_every_shell_command_is_classified`` until someone classifies it; so does a classification whose
command is gone.
``test_a_broken_command_fails`` shows the runner failing on a deliberately broken copy of a command.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Dict, Tuple

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from doc_commands import ALL_COMMANDS, Command, make_clone, run_command, shell_commands  # noqa: E402

pytest.importorskip("spconv", reason="the documented commands run the example detectors (the examples extra)")

_REGISTRY = "installs from the package registry (network; changes the environment); tests/project/test_packaging.py " \
            "builds the wheel with the same PEP 517 hooks and installs it, with its `mssf` script"
_NOT_PUBLISHED = "from the registry once a release is published (not there yet, as the doc says)"
_SUITE = "runs these test files, which are part of `make test` itself"
_GPU = "needs a CUDA GPU (CI has none); the same CLI code runs on the CPU in real-data.md's commands, and " \
       "tests/examples/training/test_distributed.py covers --device / --amp / --workers / torchrun on the CPU"

_AUTHORS = "needs the authors' released checkpoint (not available offline); tests/examples/cli/test_authors_cli.py " \
           "runs the same two commands on a fabricated checkpoint of their key list and a generated VoD tree"

NOT_RUN_FILES: Dict[str, str] = {
    "docs/frameworks.md": "run by tests/integrations (the framework tests, which need the real OpenPCDet / "
                          "mmdetection3d and say so)",
}

NOT_RUN: Dict[Tuple[str, str], str] = {
    ("README.md", 'pip install -e ".[examples]"'): _REGISTRY + "; the Makefile runs the same install",
    ("README.md", "pip install build"): _REGISTRY,
    ("README.md", "python -m build --wheel"):
        "`build` makes an isolated environment from the registry; tests/project/test_packaging.py calls the same "
        "setuptools hooks offline",
    ("README.md", 'pip install --find-links dist "mssf-blocks[examples]"'): _REGISTRY,
    ("README.md", "pip install mssf-blocks"): _NOT_PUBLISHED,
    ("README.md", 'pip install "mssf-blocks[examples]"'): _NOT_PUBLISHED,
    ("README.md", 'pip install "mssf-blocks[plot]"'): _NOT_PUBLISHED,
    ("docs/index.md", 'pip install -e ".[examples]"'): _REGISTRY + "; the Makefile runs the same install",
    ("docs/index.md", "pip install mssf-blocks"): _NOT_PUBLISHED,
    ("docs/index.md", 'pip install "mssf-blocks[examples]"'): _NOT_PUBLISHED,
    ("docs/index.md", 'pip install "mssf-blocks[plot]"'): _NOT_PUBLISHED,
    ("README.md", "make demo"): "6-10 minutes; tests/examples/training/test_train_demo.py runs the demo script with --quick "
                                "(and docs/demo.md's --quick line runs here)",
    ("docs/real-data.md", 'pip install "vod-tudelft==1.0.3" numba'):
        "installs from the package registry (network; changes the environment); `make test` installs vod-tudelft --no-deps and numba, and "
        "tests/examples/evaluation/test_evaluation_vod_kit.py loads the kit's evaluation modules by path (no k3d)",
    ("docs/index.md", "make demo"): "as README.md's `make demo`",
    ("README.md", "make test"): "the suite this test is part of",
    ("docs/index.md", "make test"): "the suite this test is part of",
    ("docs/compatibility.md", "make test-compat"): "what .ci/run runs after `make test` in CI (builds the floor and newest torch environments, minutes)",
    ("docs/compatibility.md", "COMPAT_DIR=/tmp/envs bash .ci/compat_envs.sh"): "the same script as `make test-compat`, run by CI; a second copy of its environments here would take minutes and GBs",
    ("docs/demo.md", "python examples/train_demo.py"): "`make demo` itself (6-10 minutes); its --quick line runs",
    ("docs/demo.md", "python examples/train_demo.py --lighting --save-checkpoint outputs/demo/ckpt.pt"):
        "a full demo run; tests/examples/training/test_train_demo.py runs --quick --lighting --save-checkpoint",
    ("docs/demo.md", "python examples/train_demo.py --steps 800 --seed 1 --out outputs/demo_s1"):
        "a full demo run (minutes)",
    ("docs/demo.md", "python examples/train_demo.py --load-checkpoint outputs/demo/ckpt.pt"):
        "needs the checkpoint of a full demo run; tests/examples/training/test_train_demo.py runs --quick --load-checkpoint",
    ("docs/fusion.md", "pytest tests/samplers/test_sff.py tests/samplers/test_msdff.py tests/blocks/test_fusion_block.py "
                       "tests/examples/models/test_swap_example.py -q"): _SUITE,
    ("docs/real-data.md", "python -m pytest tests/examples/data/test_kitti_io.py tests/examples/data/test_kitti_boxes.py "
                          "tests/examples/data/test_kitti_layouts.py tests/examples/data/test_real_frame.py -q"): _SUITE,
    ("docs/real-data.md", "MSSF_REALDATA=/path/to/realdata python -m pytest -m realdata -q"):
        _SUITE + " (with ../shared/realdata, as in CI)",
    ("docs/gpus.md", "mssf train --dataset vod --data-root /data/view_of_delft --detector pointpillars --device cuda "
                     "--amp bf16 --workers 8 --batch-size 4 --image-weights resnet50_fpn.pt --out outputs/vod_pp"): _GPU,
    ("docs/gpus.md", "PYTHONPATH=src:examples torchrun --standalone --nproc_per_node 4 -m mssf_examples train "
                     "--dataset vod --data-root /data/view_of_delft --detector centerpoint --device cuda --amp bf16 "
                     "--batch-size 16 --workers 4 --sync-bn --image-weights resnet50_fpn.pt --out outputs/vod_cp_4gpu"): _GPU,
    ("docs/gpus.md", "PYTHONPATH=src:examples torchrun --nnodes 2 --nproc_per_node 8 --rdzv-backend c10d "
                     "--rdzv-endpoint node0:29500 --rdzv-id vod_cp_16gpu -m mssf_examples train --dataset vod "
                     "--data-root /data/view_of_delft --detector centerpoint --device cuda --amp bf16 --batch-size 64 "
                     "--sync-bn --image-weights resnet50_fpn.pt --out /shared/outputs/vod_cp_16gpu"): "two nodes of 8 GPUs; " + _GPU,
    ("docs/gpus.md", "make gpu-check"): "the device check for a GPU machine; tests/project/test_gpu_check.py runs its "
                                        "--smoke --device cpu mode",
    ("docs/gpus.md", "python benchmarks/gpu_check.py --skip-install --mmcv-src mmcv-2.1.0.tar.gz --out "
                     "outputs/gpu_check"): "the device check with mmcv's op built from its source archive: a GPU "
                                           "machine; tests/project/test_mmcv_build.py checks the sources it takes and the binding",
    ("docs/differences.md", "python -m mssf_examples convert-authors mssf_pp_vod.pth --out converted/mssf_pp.pt "
                            "--layout mssf_pp"): _AUTHORS,
    ("docs/differences.md", "python -m mssf_examples eval --checkpoint converted/mssf_pp.pt --data-root "
                            "/data/view_of_delft --split val"): _AUTHORS,
}

#: commands that run exactly as printed (placeholders aside), in page order
RUN = {
    ("README.md", "python examples/quickstart.py"),
    ("README.md", "mssf eval --checkpoint outputs/vod/checkpoint.pt --data-root /data/view_of_delft --split val "
                  "--out outputs/vod/val"),
    ("docs/demo.md", "python examples/train_demo.py --quick --out /tmp/demo"),
    ("docs/deployment.md", 'python -c "import torch, mssf_blocks; print(torch.__version__)"'),
    ("docs/deployment.md", "python examples/export_onnx.py --out mssf_pointpillars.onnx --fusion msdff --blocks 2 "
                           "--preset tiny"),
    ("docs/real-data.md", "python examples/real_frame.py --data-root ../shared/realdata/vod --frame 00549 "
                          "--out /tmp/real_frame"),
    ("docs/real-data.md", "python examples/real_frame.py --data-root /data/view_of_delft --sensor radar_5frames "
                          "--frame 00100 --out out/"),
    ("docs/real-data.md", "mssf --help"),
    ("docs/real-data.md", "mssf train --help"),
    ("docs/real-data.md", "python -m mssf_examples eval --help"),
    ("docs/real-data.md", "mssf eval --checkpoint outputs/vod_pp_n2/checkpoint.pt --data-root /data/view_of_delft "
                          "--split val --out outputs/vod_pp_n2/val"),
    ("docs/real-data.md", "mssf eval --checkpoint outputs/vod_pp_n2/checkpoint.pt --data-root /data/view_of_delft "
                          "--split test --out outputs/vod_pp_n2/test"),
    ("docs/real-data.md", "mssf train --dataset vod --data-root /data/view_of_delft --preset tiny --image-scale 0.5 "
                          "--steps 20 --batch-size 2 --val-split val --out /tmp/vod_smoke"),
}

_SHORT = {"--epochs 80": "--steps 2 --preset tiny"}
#: the paper preset's frozen image branch needs the reader's own pre-trained weights (no test has a ResNet-50
#: file); the tiny preset trains its branch, so the shortened runs leave the option out
_NO_WEIGHTS = {"--image-weights resnet50_fpn.pt ": ""}
SHORTENED: Dict[Tuple[str, str], Tuple[Dict[str, str], str]] = {
    ("README.md", "mssf train --dataset vod --data-root /data/view_of_delft --image-weights resnet50_fpn.pt "
                  "--out outputs/vod"):
        ({**_NO_WEIGHTS, "--out outputs/vod": "--steps 2 --preset tiny --out outputs/vod"}, "the default 80 epochs"),
    ("docs/real-data.md", "mssf train --dataset vod --data-root /data/view_of_delft --detector pointpillars "
                          "--fusion-blocks 2 --fusion msdff --epochs 80 --batch-size 4 --lr 3e-3 --image-weights "
                          "resnet50_fpn.pt --val-split val --out outputs/vod_pp_n2"): ({**_SHORT, **_NO_WEIGHTS}, "80 epochs"),
    ("docs/real-data.md", "mssf train --dataset tj4d --data-root /data/TJ4DRadSet --detector centerpoint "
                          "--fusion-blocks 0 --val-split val --out outputs/tj4d_cp_n0"):
        ({"--out outputs/tj4d_cp_n0": "--steps 2 --preset tiny --out outputs/tj4d_cp_n0"}, "the default 80 epochs"),
    ("docs/training.md", "mssf train --dataset vod --data-root /data/view_of_delft --detector voxelnext "
                         "--fusion-blocks 2 --epochs 80 --batch-size 8 --image-weights resnet50_fpn.pt "
                         "--val-split val --out outputs/vod_voxelnext_n2"):
        ({**_SHORT, "--batch-size 8": "--batch-size 2", "--image-weights resnet50_fpn.pt ": ""},
         "80 epochs; the generated tree has 4 training frames; resnet50_fpn.pt is the reader's own weights "
         "file for the paper preset's image branch (no test loads one)"),
    ("docs/gpus.md", "mssf train --dataset vod --data-root /data/view_of_delft --image-weights resnet50_fpn.pt "
                     "--steps 3000 --checkpoint-every 500 --out outputs/run"):
        ({**_NO_WEIGHTS, "--steps 3000 --checkpoint-every 500": "--steps 4 --checkpoint-every 2 --preset tiny"},
         "3000 steps"),
    ("docs/gpus.md", "mssf train --dataset vod --data-root /data/view_of_delft --image-weights resnet50_fpn.pt "
                     "--steps 3000 --checkpoint-every 500 --out outputs/run --resume outputs/run/checkpoints/step_001500.pt"):
        ({**_NO_WEIGHTS, "--steps 3000 --checkpoint-every 500": "--steps 4 --checkpoint-every 2 --preset tiny",
          "step_001500.pt": "step_000002.pt"}, "resumes the shortened run above at its step 2"),
}

#: commands that read ../shared/realdata (skipped with it absent, like the other real-data tests)
NEEDS_REALDATA = {("docs/real-data.md", "python examples/real_frame.py --data-root ../shared/realdata/vod "
                                        "--frame 00549 --out /tmp/real_frame")}


def classify(commands) -> Dict[Tuple[str, str], str]:
    """``{key: "run" | "shortened" | "not run" | "unclassified"}``."""
    out = {}
    for c in commands:
        if c.not_run or c.file in NOT_RUN_FILES or c.key in NOT_RUN:
            out[c.key] = "not run"
        elif c.key in SHORTENED:
            out[c.key] = "shortened"
        elif c.key in RUN:
            out[c.key] = "run"
        else:
            out[c.key] = "unclassified"
    return out


def test_every_shell_command_is_classified():
    keys = [c.key for c in ALL_COMMANDS]
    kinds = classify(ALL_COMMANDS)
    unclassified = [f"{c.where}: {c.text}" for c in ALL_COMMANDS if kinds[c.key] == "unclassified"]
    assert not unclassified, (
        "shell commands in README.md / docs/*.md that tests/docs/test_docs_commands.py does not know: add each to RUN "
        "(it runs as printed), SHORTENED or NOT_RUN with the reason, or mark its block "
        "`<!-- commands: not run: REASON -->`:\n  " + "\n  ".join(unclassified))
    lists = [set(RUN), set(NOT_RUN), set(SHORTENED)]
    both = [k for i, a in enumerate(lists) for b in lists[i + 1:] for k in a & b]
    assert not both, f"listed twice: {sorted(both)}"
    assert NEEDS_REALDATA <= RUN
    stale = sorted((RUN | set(NOT_RUN) | set(SHORTENED)) - set(keys))
    assert not stale, f"classified commands no longer in the docs (text changed or removed): {stale}"
    for key, (replace, reason) in SHORTENED.items():
        assert reason and all(old in key[1] for old in replace), (key, replace)
    assert all(reason.strip() for reason in list(NOT_RUN.values()) + list(NOT_RUN_FILES.values()))


def test_classification_catches_a_new_command(tmp_path):
    """A page with a new command: it is "unclassified" (test_every_shell_command_is_classified fails on it)
    until listed or marked; a marked block is "not run" with the marker's reason."""
    (tmp_path / "docs").mkdir()
    page = tmp_path / "docs" / "new.md"
    page.write_text("```bash\nmssf --version-that-does-not-exist   # new\n```\n\n"
                    "<!-- commands: not run: needs a GPU -->\n```console\n$ nvidia-smi \\\n    -L\nGPU 0\n```\n")
    cmds = shell_commands(page, root=tmp_path)
    assert [(c.line, c.text, c.not_run) for c in cmds] == [
        (2, "mssf --version-that-does-not-exist", None), (7, "nvidia-smi -L", "needs a GPU")]
    assert classify(cmds) == {cmds[0].key: "unclassified", cmds[1].key: "not run"}


@pytest.fixture(scope="module")
def clone(tmp_path_factory):
    bindir = Path(sys.executable).parent
    if shutil.which("mssf", path=str(bindir)) is None:  # the docs assume an install (README, "Install")
        msg = f"no `mssf` script beside {sys.executable}: the documented commands need pip install -e \".[examples]\""
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg)
        pytest.skip(msg)
    return make_clone(tmp_path_factory.mktemp("docs_commands"))


def _runnable(page=None):
    return [c for c in ALL_COMMANDS if (page is None or c.file == page) and classify([c])[c.key] in ("run", "shortened")]


PAGES = sorted({c.file for c in _runnable() if c.key not in NEEDS_REALDATA})


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES)
def test_documented_commands_run(page, clone):
    """The page's runnable commands, in page order, in one clone (the real-data ones: the next test)."""
    ran = 0
    for c in _runnable(page):
        if c.key in NEEDS_REALDATA:
            continue
        run_command(c, clone, SHORTENED[c.key][0] if c.key in SHORTENED else None)
        ran += 1
    assert ran


@pytest.mark.realdata
def test_documented_realdata_commands_run(clone, realdata_root):
    """The commands that read ../shared/realdata (skipped without it, like the other real-data tests)."""
    shared = clone.parent / "shared"
    if not shared.exists():  # the frames come from $MSSF_REALDATA: put them where the doc's path expects them
        shared.mkdir()
        (shared / "realdata").symlink_to(realdata_root.resolve())
    assert (shared / "realdata").is_dir(), f"{shared}/realdata: the documented ../shared/realdata is missing"
    for key in sorted(NEEDS_REALDATA):
        run_command(next(c for c in ALL_COMMANDS if c.key == key), clone)


def test_a_broken_command_fails(clone, tmp_path):
    """A deliberately broken copy of README.md (its training line with an option misspelt, as a renamed
    CLI option would leave it): the runner fails on it, naming the copy's line (the original line runs in
    ``test_documented_commands_run[README.md]``)."""
    readme = (clone / "README.md").read_text(encoding="utf-8")
    line = "mssf train --dataset vod --data-root /data/view_of_delft --image-weights resnet50_fpn.pt --out outputs/vod"
    assert readme.count(line) == 1
    (tmp_path / "README.md").write_text(readme.replace(line, line.replace("--data-root", "--data-rot")))
    broken = next(c for c in shell_commands(tmp_path / "README.md", root=tmp_path) if "--data-rot" in c.text)
    original = next(c for c in ALL_COMMANDS if c.key == ("README.md", line))
    assert broken.line == original.line
    with pytest.raises(AssertionError, match=rf"README.md:{original.line}: the documented command failed"
                                             r"(.|\n)*unrecognized arguments: --data-rot"):
        run_command(broken, clone)
