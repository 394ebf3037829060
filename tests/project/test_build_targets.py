"""The Makefile's benchmark targets and the docs site configuration (mkdocs.yml + mkdocs_hooks.py)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
# every CPU benchmark script (gpu_check.py is the GPU machine's device check: `make gpu-check`; gpu_bundle.py
# builds what that machine carries: `make gpu-bundle`)
BENCHMARKS = sorted(p.stem for p in (REPO / "benchmarks").glob("*.py")
                    if not p.name.startswith("_") and p.stem not in ("gpu_check", "gpu_bundle"))


def _make_n(target: str, tmp_path: Path) -> str:
    """``make -n target`` with an up-to-date install stamp (no venv set-up lines) and PY=python."""
    if shutil.which("make") is None:
        pytest.skip("make not installed")
    stamp = tmp_path / "stamp"
    stamp.touch()
    os.utime(stamp, (2**31, 2**31))  # newer than pyproject.toml
    r = subprocess.run(["make", "-n", "--no-print-directory", target, f"STAMP={stamp}", "PY=python"], cwd=REPO,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def test_benchmarks_exist():
    assert {"centroids", "msdff", "detectors", "threads"} <= set(BENCHMARKS)


@pytest.mark.parametrize("name", BENCHMARKS)
def test_every_benchmark_has_a_make_target(name, tmp_path):
    out = _make_n(f"bench-{name}", tmp_path)
    assert out.split("\n")[0].split() == ["python", f"benchmarks/{name}.py"], out


def test_make_bench_runs_them_all(tmp_path):
    lines = [l.split() for l in _make_n("bench", tmp_path).splitlines() if l.strip()]
    assert lines == [["python", f"benchmarks/{n}.py"] for n in BENCHMARKS]


def test_performance_doc_gives_each_benchmark_a_duration():
    text = (REPO / "docs" / "performance.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| `make bench-([\w-]+)` \| `benchmarks/[\w-]+\.py` \| ([^|]+) \|", text, re.M)
    missing = set(BENCHMARKS) - {n for n, _ in rows}
    assert not missing, f"add a row for {sorted(missing)} to the table in docs/performance.md, 'Benchmark targets'"
    assert all(re.search(r"\d", d) for _, d in rows)


def test_mkdocs_config_builds_from_docs_without_explicit_nav():
    text = (REPO / "mkdocs.yml").read_text(encoding="utf-8")
    assert re.search(r"^docs_dir: docs$", text, re.M) and re.search(r"^strict: true$", text, re.M)
    assert not re.search(r"^nav:", text, re.M), "no explicit nav: pages appear without an edit here"
    assert re.search(r"^hooks:\n  - mkdocs_hooks.py$", text, re.M)


def _site(tmp_path: Path, page: str) -> subprocess.CompletedProcess:
    """A site like ours (same config and hook) whose docs/ is one page; a file outside docs/ exists."""
    pytest.importorskip("mkdocs")
    root = tmp_path / "repo"
    (root / "docs").mkdir(parents=True)
    (root / "examples").mkdir()
    (root / "examples" / "demo.py").write_text("print()\n")
    shutil.copy(REPO / "mkdocs.yml", root / "mkdocs.yml")
    shutil.copy(REPO / "mkdocs_hooks.py", root / "mkdocs_hooks.py")
    (root / "docs" / "index.md").write_text(page)
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
                          cwd=root, capture_output=True, text=True, timeout=300)


def test_links_outside_docs_point_at_the_repository(tmp_path):
    r = _site(tmp_path, "# x\n\nRun [the demo](../examples/demo.py) or [a folder](../examples/).\n\n"
                        "```python\ns = '[not a link](../nope.py)'\n```\n")
    assert r.returncode == 0, r.stdout + r.stderr
    html = (tmp_path / "site" / "index.html").read_text()
    assert 'href="https://github.com/mssf-blocks/mssf-blocks/blob/main/examples/demo.py"' in html
    assert 'href="https://github.com/mssf-blocks/mssf-blocks/tree/main/examples"' in html


@pytest.mark.parametrize("link", ["../examples/missing.py", "missing.md"])
def test_a_broken_link_fails_the_strict_build(tmp_path, link):
    r = _site(tmp_path, f"# x\n\nSee [this]({link}).\n")
    assert r.returncode != 0
    assert link.split("/")[-1] in r.stdout + r.stderr
