"""benchmarks/static_path.py --smoke: the script runs end to end (MSDFF and the detector, eager / static /
onnxruntime) and its three paths agree, so that the benchmark cannot rot. No timing is asserted."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _run_smoke(tmp_path, *extra):
    """``(stdout, rows)`` of ``benchmarks/static_path.py --smoke *extra``, asserting it exits 0."""
    path = [str(REPO / "src"), str(REPO / "examples"), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(path))
    out = tmp_path / "rows.json"
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "static_path.py"), "--smoke", *extra, "--json",
                        str(out)], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    return r.stdout, json.loads(out.read_text())


def test_static_path_benchmark_smoke_runs_and_its_paths_agree(tmp_path):
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    stdout, rows = _run_smoke(tmp_path)
    floors = [row for row in rows if "static floor ms" in row]
    rows = [row for row in rows if "static floor ms" not in row]
    cases = [row["case"] for row in rows]
    assert sum(c.startswith("MSDFF N=") for c in cases) == 4
    assert cases[-2].startswith("MSSF-PointPillars") and cases[-1].startswith("radar-only PointPillars")
    # the floors (benchmarks/_static_floors.py; their ONNX graphs check their own sums): one per case,
    # four levels each, every time positive, the static floor no more than the static path it bounds plus noise
    assert [f["case"] for f in floors] == ["MSDFF N=40 channels-last", "MSDFF N=40 NCHW", "MSDFF N=70 channels-last",
                                           "MSDFF N=70 NCHW"]
    for f in floors:
        assert f["ONNX floor ms"] > 0 and f["static floor ms"] > 0
        assert len(f["static levels (raw / projected) ms"].split()) == 2  # (the smoke configuration's 2 levels)
        assert len(f["ONNX levels (Conv / Gather / GridSample) ms"].split()) == 2
    assert "Floors of any exact static-shape sampling" in stdout
    for row in rows:
        for path in ("static", "exported"):
            assert row[f"{path} ms"] > 0
            assert float(row[f"{path} max diff"]) <= 1e-4, row  # the same function, three ways
    assert "| case | eager ms | static ms | exported ms |" in stdout


def test_static_path_block_size_sweep_smoke_runs(tmp_path):
    """``--block-mib``: one row per voxel count, one ratio per block size (0: one block of every query)."""
    _, rows = _run_smoke(tmp_path, "--block-mib", "1", "0")
    assert [row["case"] for row in rows] == ["MSDFF N=40 channels-last", "MSDFF N=70 channels-last"]
    for row in rows:
        assert row["eager ms"] > 0 and row["1 MiB / eager"] > 0 and row["one block / eager"] > 0
