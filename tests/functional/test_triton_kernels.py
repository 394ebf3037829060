"""The sampling op's Triton kernels, checked on a machine without a GPU.

* numerics: ``triton_interpret_cases.py`` runs the kernels on CPU tensors under ``TRITON_INTERPRET=1``
  against the float64 references, in a fresh pytest process (the interpreter must be on before
  ``triton`` is first imported);
* compile: ``triton_aot.py`` compiles every kernel variant ahead of time for sm_80 and sm_90 in a
  process *without* the interpreter and reads the registers and spills of the cubin; none may spill.

``triton`` is in the dev extra on Linux x86_64: a user's clone without it skips these tests, CI
(``CI=true``) fails instead.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent

if importlib.util.find_spec("triton") is None:
    if os.environ.get("CI") == "true":
        raise RuntimeError("triton is not installed: CI needs it (pip install -e '.[dev]' on Linux x86_64)")
    pytest.skip("triton is not installed (pip install triton, or the dev extra on Linux x86_64)",
                allow_module_level=True)


def _env(**extra):
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONPATH"] = os.pathsep.join([str(HERE), str(HERE.parent / "references"), env.get("PYTHONPATH", "")])
    env.update(extra)
    return env


def junit_counts(path: Path) -> dict:
    """``{"tests", "failures", "errors", "skipped"}`` summed over the suites of a ``--junitxml`` report (not
    the printed output: with ``-rA`` in ``PYTEST_ADDOPTS`` it also lists test names, and one contains
    the word "skipped")."""
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else root.iter("testsuite")
    counts = dict.fromkeys(("tests", "failures", "errors", "skipped"), 0)
    for suite in suites:
        for key in counts:
            counts[key] += int(suite.get(key, 0))
    return counts


def test_kernels_match_float64_references_under_the_interpreter(tmp_path):
    report = tmp_path / "interpreter.xml"
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
         f"--junitxml={report}", "triton_interpret_cases.py"],
        cwd=HERE, env=_env(TRITON_INTERPRET="1"), capture_output=True, text=True, timeout=300,
    )
    assert res.returncode == 0, res.stdout[-6000:] + res.stderr[-3000:]
    counts = junit_counts(report)
    assert counts["tests"] > 0 and counts == {"tests": counts["tests"], "failures": 0, "errors": 0, "skipped": 0}, (
        counts, res.stdout[-2000:])


def test_every_kernel_variant_compiles_for_sm80_and_sm90_without_spills():
    res = subprocess.run([sys.executable, str(HERE / "triton_aot.py"), "80", "90"], cwd=HERE, env=_env(),
                         capture_output=True, text=True, timeout=400)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-6000:]
    rows = [json.loads(line) for line in res.stdout.splitlines() if line.startswith("{")]
    kinds = {(r["kernel"], r["cc"], r["dtype"], r["d"]) for r in rows}
    assert len(kinds) == len(rows) == 3 * 2 * 3 * 3, sorted(kinds)  # kernels x targets x dtypes x widths
    spilled = [r for r in rows if r["spill_stores"] or r["spill_loads"] or r["stack_bytes"] or r["local_bytes"]]
    assert not spilled, spilled
    assert all(0 < r["registers"] <= 255 for r in rows), rows


def test_junit_counts_see_a_skip_whatever_the_output_prints(tmp_path):
    """The counts the interpreter test reads: a skip is counted, a test named ``..._skipped_...`` is not,
    with ``-rA`` in ``PYTEST_ADDOPTS`` (which printed that name, and the word check took it for a skip)."""
    (tmp_path / "test_cases.py").write_text(
        "import pytest\n\ndef test_a_skipped_value():\n    pass\n\n"
        "def test_b():\n    pytest.skip('no GPU')\n")
    report = tmp_path / "r.xml"
    env = {**os.environ, "PYTEST_ADDOPTS": "-rA"}
    res = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                          f"--junitxml={report}", "test_cases.py"], cwd=tmp_path, env=env, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0 and "test_a_skipped_value" in res.stdout, res.stdout
    assert junit_counts(report) == {"tests": 2, "failures": 0, "errors": 0, "skipped": 1}
