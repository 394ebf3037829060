"""``benchmarks/gpu_check.py --smoke --device cpu``: every stage of the GPU check runs (toy sizes) and the
JSON / Markdown report holds what the GPU run will fill in (so the script is known to work before a GPU
machine runs it)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mssf_blocks import _compat

pytest.importorskip("spconv")

REPO = Path(__file__).resolve().parent.parent


def test_gpu_check_smoke_on_the_cpu(tmp_path):
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples"), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--smoke", "--device", "cpu",
                        "--skip-install", "--repeats", "1", "--out", str(tmp_path)],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    result = json.loads((tmp_path / "gpu_check.json").read_text())
    assert result["smoke"] and result["environment"]["device"] == "cpu"
    assert result["tests"]["returncode"] == 0 and "passed" in result["tests"]["summary"]
    rows = result["msdff"]
    assert {(r["N"], r["precision"]) for r in rows} == {(n, p) for n in (50, 200) for p in ("float32", "bf16 autocast")}
    for row in rows:  # the reference and ours compute the same thing
        assert row["max_abs_diff"] < (1e-4 if row["precision"] == "float32" else 5e-2)
        assert row["fwd_ratio"] > 0 and row["fwd_bwd_ratio"] > 0
    assert [d["detector"] for d in result["detectors"]] == ["second", "centerpoint", "voxelnext", "pointpillars"]
    assert all(d["loss_finite"] and d["step_ms"] > 0 for d in result["detectors"])
    pp = result["detectors"][-1]  # PointPillars (pure torch) also steps under CPU autocast
    assert pp["bf16_step_ms"] > 0 and pp["bf16_loss_finite"]
    if _compat.has("cpu_float16_autocast"):
        assert pp["fp16_step_ms"] > 0 and pp["fp16_loss_finite"]
    else:  # torch 2.1: the report says why there is no float16 row
        assert pp["fp16_step_ms"] == f"n/a ({_compat.missing('cpu_float16_autocast')})"
    assert result["detectors"][0]["bf16_step_ms"] == "n/a (spconv CPU)"
    assert [(r["N"], r["dtype"]) for r in result["sampling"]] == [(50, "float32"), (50, "bfloat16")]
    assert all(r["grid_fwd_ms"] > 0 and r["grid_fwd_bwd_ms"] > 0 for r in result["sampling"])
    mm = result["mmdet3d"]  # stage 4: trained where mmdet3d with mmcv's ops imports (make test installs them)
    try:
        import mmcv._ext  # noqa: F401
        import mmdet3d  # noqa: F401
        has_mmdet3d = True
    except ImportError:
        has_mmdet3d = os.environ.get("CI", "").lower() == "true"  # CI installs them: then the stage must run
    if has_mmdet3d:
        assert mm["iters"] == 2 and mm["iter_s"] > 0 and mm["loss_finite"], mm
    else:
        assert mm["skipped"].startswith("not run: mmdet3d with mmcv's compiled ops does not import"), mm
    md = (tmp_path / "gpu_check.md").read_text()
    assert "## The shipped mmdet3d config" in md
    assert "## Sampling core" in md
    assert "## MSDFF" in md and "## One training step per detector" in md and "pointpillars" in md


def test_gpu_check_refuses_a_missing_gpu_clearly(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples")]))
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--skip-install", "--out",
                        str(tmp_path)], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    assert "sees no CUDA GPU" in r.stderr and "--smoke --device cpu" in r.stderr
