"""benchmarks/roofline.py --quick: the script runs end to end (one-core ceilings, eager MSDFF against the
reference and against the roofline), eager agrees with the reference, and its counts are the hand-worked
ones, so that the benchmark cannot rot. No timing is asserted."""

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_roofline_benchmark_quick_runs_and_counts_its_reads(tmp_path):
    path = [str(REPO / "src"), str(REPO / "examples"), os.environ.get("PYTHONPATH", "")]
    env = dict(os.environ, OMP_NUM_THREADS="1", PYTHONPATH=os.pathsep.join(path))
    out = tmp_path / "roofline.json"
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "roofline.py"), "--quick", "--json", str(out)],
                       check=False, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    result = json.loads(out.read_text())
    units = [c["unit"] for c in result["ceilings"]]
    assert units.count("GFLOP/s") == 2 and units.count("M rows/s") == 12 and units.count("GB/s") == 1
    assert all(c["rate"] > 0 for c in result["ceilings"])
    rows = result["rows"]
    assert [(row["N"], row["voxels"]) for row in rows] == [
        (300, "uniform"), (1000, "uniform"), (300, "radar band"), (1000, "radar band")]
    for row in rows:
        assert float(row["max|out diff|"]) <= 1e-4, row  # the same function, two formulations
        # N x 8 heads x 4 levels x 4 points x 4 bilinear corners, worked by hand
        assert row["corner reads (M)"] * 1e6 == row["N"] * 8 * 4 * 4 * 4
        assert row["eager ms"] > 0 and row["reference ms"] > 0 and row["roofline bound ms"] > 0
        assert len(row["bound plan"].split("/")) == 4
        # the bound is the larger of its gather and FMA times
        assert row["roofline bound ms"] == max(row["bound gather ms"], row["bound FMA ms"])
        assert abs(row["reference / bound"] * row["roofline bound ms"] - row["reference ms"]) < 1e-6 * row["reference ms"]
    assert "| N | C | voxels | eager ms | reference ms | reference / eager |" in r.stdout
