"""The distributions: the wheel holds both packages and works installed; the sdist is a runnable tree.

Both are built (PEP 517, setuptools, no network) from a copy of the source tree. Checks:

* wheel: ``mssf_blocks`` and ``mssf_examples`` (every module of both), nothing else; unpacked
  outside the repository, ``python -m mssf_examples --help`` runs from it; ``pip install`` of it writes the
  ``mssf`` console script, which runs the same CLI, and the README's ``mssf train`` / ``mssf eval`` lines run
  with it on a generated View-of-Delft tree; the ``examples`` extra
  lists exactly the third-party packages ``mssf_examples`` imports beyond the core dependencies;
* sdist: every file of the source tree (tests with conftest.py and sub-folders, docs, examples,
  benchmarks, Makefile, mkdocs.yml), and pytest collects the suite from the unpacked sdist with no error.
"""

from __future__ import annotations

import ast
import email
import os
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
_IGNORE = shutil.ignore_patterns(".git", ".venv", "__pycache__", "*.egg-info", ".pytest_cache", ".hypothesis",
                                 "build", "dist", "outputs", "*.pt", "*.pyc", "site", "results", ".carry")
# import name -> distribution name, for the examples' third-party imports
_DIST_OF = {"PIL": "pillow", "spconv": "spconv", "tqdm": "tqdm", "torch": "torch", "numpy": "numpy",
            "einops": "einops", "matplotlib": "matplotlib"}

setuptools = pytest.importorskip("setuptools")
if tuple(int(x) for x in re.findall(r"\d+", setuptools.__version__)[:1]) < (77,):
    pytest.skip(f"needs setuptools>=77 (the dev extra), found {setuptools.__version__}", allow_module_level=True)


def _tree_files(root: Path):
    return {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """``(source copy, its files before the build, sdist path, wheel path)``."""
    tmp = tmp_path_factory.mktemp("dist")
    src = tmp / "src"
    shutil.copytree(REPO, src, ignore=_IGNORE)
    files = _tree_files(src)
    out = tmp / "out"
    names = []
    for hook in ("build_sdist", "build_wheel"):  # one process each, as a PEP 517 frontend does
        code = f"import sys; from setuptools import build_meta as b; print(b.{hook}(sys.argv[1]))"
        r = subprocess.run([sys.executable, "-c", code, str(out)], cwd=src, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stdout + r.stderr
        names.append(r.stdout.strip().splitlines()[-1])
    return src, files, out / names[0], out / names[1]


def test_wheel_holds_both_packages_and_nothing_else(built):
    src, _, _, wheel = built
    names = set(zipfile.ZipFile(wheel).namelist())
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"mssf_blocks", "mssf_examples"}, tops
    for pkg, root in (("mssf_blocks", src / "src" / "mssf_blocks"), ("mssf_examples", src / "examples" / "mssf_examples")):
        want = {f"{pkg}/{p}" for p in _tree_files(root) if p.endswith(".py")}
        assert want <= names, sorted(want - names)
    assert "mssf_blocks/py.typed" in names


#: mssf_examples.openpcdet runs inside an OpenPCDet install (not on the registry), whose requirements
#: provide these; they are not the examples extra's to promise
_OPENPCDET_PROVIDES = {"pcdet", "easydict", "yaml"}


def _third_party_imports(root: Path, exclude=()):
    found = set()
    for path in root.rglob("*.py"):
        if any(path.is_relative_to(root / e) for e in exclude):
            continue
        names = _third_party_imports_of(path)
        found |= names - _OPENPCDET_PROVIDES if "openpcdet" in path.relative_to(root).parts else names
    return {n for n in found if n not in sys.stdlib_module_names and n not in ("mssf_blocks", "mssf_examples")}


def _third_party_imports_of(path: Path):
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found


@pytest.mark.skipif(not hasattr(sys, "stdlib_module_names"), reason="Python >= 3.10 lists the standard library")
def test_examples_extra_promises_what_the_examples_import(built):
    src, _, _, wheel = built
    with zipfile.ZipFile(wheel) as z:
        meta = email.message_from_bytes(z.read(next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))))
    reqs = meta.get_all("Requires-Dist")
    core = {re.match(r"[\w.-]+", r).group(0).lower() for r in reqs if "extra ==" not in r}
    examples = {re.match(r"[\w.-]+", r).group(0).lower() for r in reqs if re.search(r"extra == .examples.", r)}
    # mssf_examples.mmdet3d runs inside mmdetection3d, installed as docs/frameworks.md says (not an extra:
    # mmdet3d's own requirements pull mmcv builds); it imports only the framework (mmdet3d, mmengine, and mmdet,
    # which mmdet3d requires: the HTC-shaped image checkpoint's writer) beyond the examples extra
    used = {_DIST_OF[n] for n in _third_party_imports(src / "examples" / "mssf_examples", exclude=("mmdet3d",))}
    framework = _third_party_imports(src / "examples" / "mssf_examples" / "mmdet3d")
    assert framework - {"mmdet3d", "mmengine", "mmdet"} <= {n for n in _DIST_OF if _DIST_OF[n] in examples | core}, framework
    assert core == {"torch", "numpy", "einops"}
    assert examples == used - core, f"examples extra {sorted(examples)} vs what mssf_examples imports {sorted(used)}"


def test_installed_wheel_runs_the_cli_outside_the_repository(built, tmp_path):
    _, _, _, wheel = built
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)  # a pure-Python wheel: unpacking it is installing it
    env = dict(os.environ, PYTHONPATH=str(site))
    code = ("import mssf_blocks, mssf_examples; print(mssf_blocks.__file__); print(mssf_examples.__file__)")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert all(Path(p).resolve().is_relative_to(site.resolve()) for p in r.stdout.split()), r.stdout
    pytest.importorskip("spconv")
    r = subprocess.run([sys.executable, "-m", "mssf_examples", "--help"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "usage: python -m mssf_examples" in r.stdout and "{train,eval,convert-authors}" in r.stdout


def test_wheel_installs_the_mssf_console_script(built, tmp_path):
    """``pip install`` of the wheel (offline, no dependencies) writes an ``mssf`` script that runs the
    same CLI as ``python -m mssf_examples`` (the README's install paths promise the command)."""
    _, _, _, wheel = built
    with zipfile.ZipFile(wheel) as z:
        ep = z.read(next(n for n in z.namelist() if n.endswith(".dist-info/entry_points.txt"))).decode()
    assert re.search(r"^\[console_scripts\]\s*^mssf = mssf_examples\.__main__:entry$", ep, re.M), ep
    target = tmp_path / "target"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index",
                        "--target", str(target), str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    script = target / "bin" / "mssf"
    assert script.is_file(), sorted(p.name for p in target.iterdir())
    pytest.importorskip("spconv")
    env = dict(os.environ, PYTHONPATH=str(target))
    r = subprocess.run([str(script), "--help"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "{train,eval,convert-authors}" in r.stdout
    r = subprocess.run([str(script), "train", "--dataset", "nope"], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 2 and "--dataset" in r.stderr, r.stderr  # argparse's error, through the script


def test_readme_train_and_eval_run_from_the_installed_wheel(built, tmp_path):
    """The README's "On your own data" commands, as printed (``/data/view_of_delft`` -> a generated VoD
    tree; the training run shortened as tests/docs/test_docs_commands.py shortens it), with the wheel's ``mssf``
    script and packages only (installed with ``--target``, run outside the repository)."""
    pytest.importorskip("spconv")
    sys.path.insert(0, str(REPO / "tests" / "docs"))
    from doc_commands import ALL_COMMANDS, run_command, write_vod_and_tj4d_trees
    from test_docs_commands import SHORTENED

    _, _, _, wheel = built
    target = tmp_path / "target"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-index",
                        "--target", str(target), str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    write_vod_and_tj4d_trees(tmp_path / "data")
    work = tmp_path / "work"
    work.mkdir()
    readme = [c for c in ALL_COMMANDS if c.file == "README.md" and c.text.startswith("mssf ")]
    assert [c.text.split()[1] for c in readme] == ["train", "eval"], [c.text for c in readme]
    for c in readme:
        r = run_command(c, work, SHORTENED.get(c.key, ({}, ""))[0], path_first=[target / "bin"], pythonpath=target)
    import json

    val = work / "outputs" / "vod" / "val"
    assert json.loads((val / "metrics.json").read_text())["protocol"] == "vod"
    assert sorted(p.stem for p in (val / "predictions").iterdir()) == ["00104", "00105"]  # the val frames
    # and it was the wheel's code that ran, not the repository's editable install
    env = dict(os.environ, PYTHONPATH=str(target))
    r = subprocess.run([sys.executable, "-c", "import mssf_examples.cli.commands as c; print(c.__file__)"], cwd=work, env=env,
                       capture_output=True, text=True)
    assert Path(r.stdout.strip()).resolve().is_relative_to(target.resolve()), r.stdout + r.stderr


def test_sdist_is_the_whole_source_tree(built):
    _, want, sdist, _ = built
    with tarfile.open(sdist) as t:
        top = t.getnames()[0].split("/")[0]
        names = {n.split("/", 1)[1] for n in t.getnames() if "/" in n and t.getmember(n).isfile()}
    extra = {n for n in names if n == "PKG-INFO" or n == "setup.cfg" or ".egg-info/" in n}
    assert {"tests/conftest.py", "tests/examples/cli/test_cli.py", "mkdocs.yml", "Makefile", "docs/index.md"} <= want
    assert names - extra == want, f"missing: {sorted(want - names)[:20]}; unexpected: {sorted(names - extra - want)[:20]}"
    assert top.startswith("mssf_blocks-")


def test_sdist_test_suite_collects(built, tmp_path):
    _, _, sdist, _ = built
    with tarfile.open(sdist) as t:
        t.extractall(tmp_path, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    root = next(tmp_path.iterdir())
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root / "src"), str(root / "examples")]))
    r = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"], cwd=root,
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert re.search(r"\d+ tests? collected", r.stdout) and "error" not in r.stdout.splitlines()[-1], r.stdout[-2000:]
