"""The commands of docs/frameworks.md ("mmdetection3d"), run in order, and its install lines against the Makefile.

Classified as tests/docs/test_docs_commands.py classifies the other pages' commands (that test leaves
docs/frameworks.md to the framework tests): each ``python -m mssf_examples.mmdet3d`` line of the section's
``bash`` blocks is in ``RUN`` (runs verbatim), ``SHORTENED`` (the texts given are replaced, each must
still be in the line, everything else as printed, with the reason) or ``NOT_RUN`` (with the reason); a
line in none, or a classified line no longer printed, fails ``test_every_command_is_classified``. They run in-process through the
entry's ``main`` in a temporary folder laid out as the docs assume (``data/view_of_delft`` a generated
VoD release tree with ``.jpg`` images and 4 training frames, ``examples`` the repository's,
``checkpoints/htc_r50_fpn.pth`` a generated HTC-shaped file where the page downloads the real one). The quick
check's run is also the training check of ``mssf_pointpillars_vod.py`` (``check_vod_run`` of
test_mmdet3d_train.py: losses, fusion gradients, the VoD keys), through a recording hook attached to the
runner the entry builds.

The section's ``pip install`` lines name exactly the packages and versions that ``make test`` installs
(the Makefile's recipe, which CI runs), so the printed lines cannot drift from what is tested, and cover what
mmengine, mmdet and mmdet3d declare (less what the page says it leaves out).
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path
from typing import Dict, Tuple

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import fake_htc_checkpoint, require_mmdet3d, write_tree  # noqa: E402
from test_mmdet3d_train import check_vod_run, recording_runners  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[2]
CONFIG = "examples/configs/mmdet3d/mssf_pointpillars_vod.py"
ENTRY = "python -m mssf_examples.mmdet3d"
HTC = "--image-checkpoint checkpoints/htc_r50_fpn.pth"

#: run exactly as printed, in page order
RUN = {
    f"{ENTRY} infos --root data/view_of_delft --sensor radar_5frames",
    f"{ENTRY} train {CONFIG} {HTC} --iters 2 --image-scale 320 200 --work-dir work_dirs/quick_check",
}
_QUICK = " --image-scale 320 200"
#: run with the given texts replaced: {line: ({printed text: replacement}, reason)}
SHORTENED: Dict[str, Tuple[Dict[str, str], str]] = {
    f"{ENTRY} test {CONFIG} work_dirs/mssf_pointpillars_vod/epoch_80.pth":
        ({"mssf_pointpillars_vod/epoch_80.pth": "quick_check/iter_2.pth" + _QUICK},
         "evaluates the quick check's checkpoint (the paper's run is not run: below)"),
    f"{ENTRY} train {CONFIG} --resume":
        ({"--resume": "--resume --work-dir work_dirs/quick_check --iters 3" + _QUICK},
         "resumes the quick check at its iteration 2 for one more"),
}
_TJ4D = "examples/configs/mmdet3d/mssf_pointpillars_tj4d.py"
#: run exactly as printed by tests/integrations/test_mmdet3d_tj4d.py (on its generated TJ4DRadSet tree)
RUN_TJ4D = [
    f"{ENTRY} infos --dataset tj4d --root data/TJ4DRadSet",
    f"{ENTRY} train {_TJ4D} {HTC} --iters 2 --image-scale 320 200 --work-dir work_dirs/quick_check_tj4d",
]
_AUTHORS = "examples/configs/mmdet3d/mssf_pointpillars_vod_authors.py"
_CONVERTED = "checkpoints/mssf_pp_authors_mmdet3d.pth"
#: run as printed by tests/integrations/test_mmdet3d_authors_pp.py (their checkpoint: random tensors under their
#: key list; the test line with --image-scale 160 100 appended)
RUN_AUTHORS = [
    f"{ENTRY} convert-authors checkpoints/mssf_pp_authors.pth --config {_AUTHORS} --out {_CONVERTED}",
    f"{ENTRY} test {_AUTHORS} {_CONVERTED}",
]
_PAPER = "the paper's 80 epochs (hours on a GPU)"
_TRAINED = _PAPER + "; {} trains this config 2 iterations (--iters, --image-scale, --data-root)"
#: not run, with the reason
NOT_RUN = {
    f"{ENTRY} train {CONFIG} {HTC}": _PAPER + "; the quick check above is this line with --iters 2 --image-scale 320 200 "
                               "--work-dir, run as printed",
    f"{ENTRY} train {_TJ4D} {HTC}": _PAPER + "; the TJ4D quick check is this line with --iters 2 --image-scale 320 200 "
                              "--work-dir, run as printed by test_mmdet3d_tj4d.py",
    f"{ENTRY} train examples/configs/mmdet3d/pointpillars_tj4d_radar.py":
        _PAPER + "; test_mmdet3d_tj4d.py trains this config 2 iterations (--iters, --image-scale, --data-root)",
    **{f"{ENTRY} train examples/configs/mmdet3d/{name}" + (f" {HTC}" if name.startswith("mssf") else "") + quick:
       (_PAPER if not quick else "the full-width quick check of MSSF-V") + "; test_mmdet3d_voxelnext.py trains this "
       "config 2 iterations at tiny widths (--iters, --image-scale, --data-root, the widths)"
       for name, quick in (("mssf_voxelnext_vod.py", " --iters 2 --image-scale 320 200 --work-dir "
                                                     "work_dirs/quick_check_voxelnext"),
                           ("mssf_voxelnext_vod.py", ""), ("voxelnext_vod_radar.py", ""),
                           ("mssf_voxelnext_tj4d.py", ""), ("voxelnext_tj4d_radar.py", ""))},
    f"{ENTRY} train examples/configs/mmdet3d/mssf_second_tj4d.py {HTC}": _TRAINED.format("test_mmdet3d_tj4d.py"),
    f"{ENTRY} train examples/configs/mmdet3d/mssf_centerpoint_tj4d.py {HTC}": _TRAINED.format("test_mmdet3d_tj4d.py"),
    f"{ENTRY} train examples/configs/mmdet3d/mssf_centerpoint_vod.py {HTC}": _TRAINED.format("test_mmdet3d_train.py"),
    f"{ENTRY} train examples/configs/mmdet3d/centerpoint_vod_radar.py": _TRAINED.format("test_mmdet3d_train.py"),
    f"{ENTRY} infos --root data/view_of_delft --sensor radar":
        "the page's tree holds radar_5frames only; test_mmdet3d_train.py writes a radar tree's infos with the same "
        "function (create_vod_infos(root, 'radar'))",
    f"{ENTRY} train examples/configs/mmdet3d/mssf_pointpillars_vod_single_scan.py {HTC}":
        _TRAINED.format("test_mmdet3d_train.py") + " on a generated single-scan tree",
}


def section() -> str:
    text = (REPO / "docs" / "frameworks.md").read_text()
    return text[text.index("## mmdetection3d"):text.index("## Conventions that differ")]


def bash_lines(text: str):
    lines = []
    for block in re.findall(r"```bash\n(.*?)```", text, re.S):
        lines += [" ".join(ln.split()) for ln in block.replace("\\\n", " ").splitlines() if ln.strip()]
    return lines


def doc_commands():
    return [ln for ln in bash_lines(section()) if ln.startswith(ENTRY)]


def test_every_command_is_classified():
    commands = doc_commands()
    known = RUN | set(RUN_TJ4D) | set(RUN_AUTHORS) | set(SHORTENED) | set(NOT_RUN)
    unclassified = [c for c in commands if c not in known]
    assert not unclassified, ("docs/frameworks.md: classify these in RUN, RUN_TJ4D, RUN_AUTHORS, SHORTENED or NOT_RUN: "
                              f"{unclassified}")
    stale = sorted(known - set(commands))
    assert not stale, f"classified commands no longer in docs/frameworks.md: {stale}"
    for cmd, (replace, reason) in SHORTENED.items():
        assert reason and all(old in cmd for old in replace), (cmd, replace)


def as_run(cmd: str):
    if cmd in SHORTENED:
        for old, new in SHORTENED[cmd][0].items():
            cmd = cmd.replace(old, new)
    return shlex.split(cmd)[3:]


def test_docs_commands_run(tmp_path, monkeypatch):
    require_mmdet3d()
    from mssf_examples.mmdet3d.cli import main

    commands = [c for c in doc_commands() if c not in RUN_TJ4D and c not in RUN_AUTHORS]
    assert [shlex.split(c)[3] for c in commands] == ["infos", "train", "train", "test", "train", "train", "train",
                                                    "train", "train", "train", "train", "infos", "train",
                                                    "train", "train", "train", "train", "train"], commands
    write_tree(tmp_path / "data" / "view_of_delft")
    (tmp_path / "data" / "view_of_delft" / "radar_5frames" / "vod_infos_train.pkl").unlink()  # the docs write it
    (tmp_path / "examples").symlink_to(REPO / "examples")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "htc_r50_fpn.pth").symlink_to(fake_htc_checkpoint())  # the page's wget
    monkeypatch.chdir(tmp_path)
    # test and --resume load mmengine's checkpoints weights-only (no TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD)
    monkeypatch.delenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", raising=False)
    built = recording_runners(monkeypatch)
    import mssf_examples.mmdet3d.checkpoints as checkpoints

    loaded, weights_only = [], checkpoints.load_from_local_weights_only

    def load_from_local_weights_only(filename, map_location=None):  # the name mmengine logs the loader by
        loaded.append(Path(filename).name)
        return weights_only(filename, map_location)

    monkeypatch.setattr(checkpoints, "load_from_local_weights_only", load_from_local_weights_only)
    for cmd in commands:
        if cmd not in NOT_RUN:
            assert main(as_run(cmd)) == 0, cmd
    assert (tmp_path / "data" / "view_of_delft" / "radar_5frames" / "vod_infos_train.pkl").is_file()
    # the quick check is test_mmdet3d_train.py's run of mssf_pointpillars_vod.py (its only overrides the data
    # root, here the docs' default, the iteration count and the image scale): checked as the other configs
    assert len(built) == 3  # quick check, test, resume
    check_vod_run(*built[0], fusion=True)
    quick = tmp_path / "work_dirs" / "quick_check"
    assert (quick / "iter_2.pth").is_file() and (quick / "iter_3.pth").is_file()  # resumed at iteration 2
    runs = sorted(quick.glob("*/*.log"))
    assert len(runs) == 2, runs  # the quick check and the resumed run (test writes to work_dirs/<config name>)
    first, resumed = (p.read_text() for p in runs)
    assert "Iter(train) [2/2]" in first and "VoD/driving_corridor/mAP/AP3D_R11" in first
    assert "resumed" in resumed.lower() and "Iter(train) [3/3]" in resumed
    # every file went through the weights-only loader (mssf_examples.mmdet3d.checkpoints): the image branch's
    # init_cfg (backbone, neck) in the quick check, the checkpoint of test and of --resume
    assert sorted(loaded) == ["htc_r50_fpn.pth"] * 2 + ["iter_2.pth"] * 2, loaded
    import torch

    unsafe = {g.replace("numpy.core.", "numpy._core.")  # numpy < 2 names its core module so
              for g in torch.serialization.get_unsafe_globals_in_checkpoint(str(quick / "iter_2.pth"))}
    assert unsafe == {"numpy._core.multiarray.scalar", "numpy._core.multiarray._reconstruct", "numpy.dtype",
                      "numpy.ndarray", "builtins.getattr", "mmengine.logging.history_buffer.HistoryBuffer",
                      "mmengine.optim.scheduler.param_scheduler.OneCycleParamScheduler"}, unsafe
    tested = "".join(p.read_text() for p in (tmp_path / "work_dirs" / "mssf_pointpillars_vod").glob("*/*.log"))
    assert "VoD/driving_corridor/mAP/AP3D_R11" in tested


# ---------------------------------------------------------------------------------------------------
# the install lines
# ---------------------------------------------------------------------------------------------------

def _specs(args):
    """``({package spec}, no_deps)`` of one ``pip install`` argument list (options dropped, quotes removed)."""
    args = [a.strip('"') for a in args]
    return {a for a in args if not a.startswith("-")}, "--no-deps" in args


def makefile_lines():
    """The Makefile's lines, continuations joined."""
    return (REPO / "Makefile").read_text().replace("\\\n", " ").splitlines()


def docs_installs():
    text = section()
    install = text[text.index("### Install"):text.index("### Prepare View-of-Delft")]
    return [_specs(shlex.split(ln, comments=True)[2:]) for ln in bash_lines(install) if ln.startswith("pip install")]


def test_install_lines_match_the_makefile():
    lines = makefile_lines()
    make = [(i, *_specs(ln.split("-m pip install", 1)[1].split())) for i, ln in enumerate(lines)
            if "$(PY) -m pip install" in ln]
    docs = docs_installs()
    assert len(docs) == 3, docs
    (lib, _), (nodeps_docs, nd), (deps_docs, d) = docs
    assert nd and not d
    # the library: the Makefile's editable install holds every extra the docs' one names
    extras = lambda specs: {e for s in specs for e in re.findall(r"^\.\[(.*)\]$", s)[0].split(",")}  # noqa: E731
    make_lib = [specs for _, specs, _ in make if any(s.startswith(".[") and "examples" in s for s in specs)]
    assert len(make_lib) == 1 and extras(lib) <= extras(make_lib[0]), (lib, make_lib)
    # the --no-deps line: the same specs, versions included, as the Makefile's mmdet3d line
    make_nodeps = [specs for _, specs, n in make if n and any(s.startswith("mmdet3d") for s in specs)]
    assert make_nodeps == [nodeps_docs], (make_nodeps, nodeps_docs)
    # the line with dependencies: the Makefile's two for mmdet3d (train / val helpers, then what mmdet3d's
    # models, datasets and evaluation import at module level, named by the comment above it)
    wanted = [specs for i, specs, n in make if not n and ("addict" in specs or "what mmdet3d's models" in lines[i - 1])]
    assert len(wanted) == 2, wanted
    make_deps = set().union(*wanted)
    assert deps_docs == make_deps, (sorted(deps_docs - make_deps), sorted(make_deps - deps_docs))
    # mmcv: the version the docs name is the Makefile's wheel and fallback version
    version = re.search(r"mim install\s+mmcv==([\d.]+)", " ".join(section().split())).group(1)
    text = "\n".join(lines)
    assert f"mmcv-{version}-*.whl" in text and f"mmcv-lite=={version}" in text


#: requirements of the --no-deps packages the page leaves out on purpose, with the reason
NOT_INSTALLED = {
    "opencv-python": "GUI build; opencv-python-headless is installed instead",
    "open3d": "visualisation only, never imported to train or evaluate",
    "tensorboard": "a logging backend the configs do not use",
    "numpy": "comes with torch (nuscenes-devkit's numpy < 2 pin is what --no-deps avoids)",
    "regex": "Windows only",
}


def _name(requirement: str) -> str:
    return re.split(r"[\s;<>=~!(\[]", requirement.strip(), 1)[0].lower().replace("_", "-")


def test_install_lines_cover_the_frameworks_requirements():
    """What mmengine, mmdet and mmdet3d declare (their installed metadata), which the ``--no-deps`` line skips,
    is on the page's other lines or named in ``NOT_INSTALLED`` with the reason: without ``numba`` (mmdet3d's) and
    ``pyyaml`` (mmengine's) every run stopped at the configs' ``custom_imports``."""
    import importlib.metadata as metadata

    (_, _), (nodeps, _), (deps, _) = docs_installs()
    given = {_name(s) for s in deps}
    missing = {}
    for dist in ("mmengine", "mmdet", "mmdet3d"):
        try:
            requires = metadata.requires(dist) or []
        except metadata.PackageNotFoundError:
            pytest.skip(f"{dist} not installed")
        assert any(_name(s) == dist for s in nodeps), (dist, nodeps)
        for req in requires:
            if "extra ==" in req:
                continue
            name = _name(req)
            if name not in given and name not in NOT_INSTALLED and not any(_name(s) == name for s in nodeps):
                missing.setdefault(dist, []).append(name)
    assert not missing, f"docs/frameworks.md's install lines lack {missing}"
    text = " ".join(section().split())
    assert all(k in text for k in ("opencv-python", "open3d", "tensorboard", "numpy < 2")), "say what is left out"
