"""``benchmarks/gpu_check.py``, the command the GPU machine runs (docs/gpus.md, "The device check"), dry-run
here: from a copy of what a device call sends (the tracked files and the untracked ones git does not
ignore: a fresh checkout) plus a stand-in bundle (``tests/helpers/gpu_bundle_stand_in.py``: two tiny packages, one
as a wheel, one repacked as ``tar.xz``), installed offline (pip without an index, proxies pointing at
nothing), every stage at toy sizes on the CPU (``--smoke --device cpu``). The JSON / Markdown report holds
what the GPU run will fill in, so the command is known to work before a GPU machine runs it."""

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mssf_blocks import torch_versions as _compat

pytest.importorskip("spconv")

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_bundle_stand_in import PROBES, build_stand_in  # noqa: E402
from test_gpu_bundle import OFFLINE  # noqa: E402


def _fresh_copy(dest: Path) -> Path:
    """What a device call sends: the tracked files and the untracked ones git does not ignore (no build
    outputs, no .venv, no .carry); the repository itself where git is unavailable."""
    try:
        out = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                             capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        return REPO
    for name in filter(None, out.split(b"\0")):
        src = REPO / os.fsdecode(name)
        if src.is_file():
            (dest / os.fsdecode(name)).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dest / os.fsdecode(name))
    return dest


def test_the_device_command_dry_runs_from_a_fresh_copy_with_the_bundle_offline(tmp_path):
    clone = _fresh_copy(tmp_path / "clone")
    bundle = clone / ".carry" / "gpu_bundle"
    build_stand_in(bundle, tmp_path / "cache")
    out, site = tmp_path / "out", tmp_path / "site"
    env = dict(os.environ, **OFFLINE, PIP_NO_INDEX="1", PIP_INDEX_URL="http://127.0.0.1:9/simple", OMP_NUM_THREADS="1",
               PYTHONPATH="")  # (the copy's src/ and examples/ are put on the path by the script itself)
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "benchmarks/gpu_check.py", "--bundle", ".carry/gpu_bundle", "--site",
                        str(site), "--out", str(out), "--smoke", "--device", "cpu", "--repeats", "1"],
                       cwd=clone, env=env, capture_output=True, text=True, timeout=600)
    seconds = time.perf_counter() - t0
    assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
    result = json.loads((out / "gpu_check.json").read_text())
    # the bundle: verified, installed offline into the site, importable in the check (and reported)
    b = result["bundle"]
    assert "error" not in b and b["target"] == str(site.resolve()), b
    assert sorted(e["provides"] for e in b["installed"]) == sorted(m for m, _, _ in PROBES)
    assert b["archives"] == {"mmcv_src": str((bundle / "mmcv-0.0.0.tar.gz").resolve())}
    for module, version, _ in PROBES:
        assert result["packages"][module] == version
    assert result["environment"]["mssf_blocks"] == str(clone / "src" / "mssf_blocks")  # the copy's library
    assert list(result["stages"]) == ["install", "tests", "sampling", "msdff", "fusion_block", "detectors", "mmdet3d"]
    assert all("done at" in v for v in result["stages"].values()), result["stages"]
    assert result["stage"] == "done" and "stopped" not in result
    assert sorted(p.name for p in out.iterdir()) == ["gpu_check.json", "gpu_check.log", "gpu_check.md", "tests.log"]
    assert result["smoke"] and result["environment"]["device"] == "cpu"
    assert result["tests"]["returncode"] == 0 and "passed" in result["tests"]["summary"]
    rows = result["msdff"]
    assert {(r["N"], r["precision"]) for r in rows} == {(n, p) for n in (50, 200) for p in ("float32", "bf16 autocast")}
    for row in rows:  # the reference and ours compute the same thing
        assert row["max_abs_diff"] < (1e-4 if row["precision"] == "float32" else 5e-2)
        assert row["fwd_ratio"] > 0 and row["fwd_bwd_ratio"] > 0
    assert [d["detector"] for d in result["detectors"]] == ["pointpillars", "second", "centerpoint", "voxelnext"]
    assert all(d["loss_finite"] and d["step_ms"] > 0 and d["infer_ms"] > 0 for d in result["detectors"])
    assert all(abs(d["infer_fps"] * d["infer_ms"] - 1e3) < 1e-6 for d in result["detectors"])
    pp = result["detectors"][0]  # PointPillars (pure torch) also steps and infers under CPU autocast
    assert pp["bf16_infer_ms"] > 0 and 0 <= pp["bf16_loss_rel_diff"] < 0.05
    assert pp["bf16_step_ms"] > 0 and pp["bf16_loss_finite"]
    if _compat.has("cpu_float16_autocast"):
        assert pp["fp16_step_ms"] > 0 and pp["fp16_loss_finite"]
    else:  # torch 2.1: the report says why there is no float16 row
        assert pp["fp16_step_ms"] == f"n/a ({_compat.missing('cpu_float16_autocast')})"
    assert result["detectors"][1]["bf16_step_ms"] == "n/a (spconv CPU)"
    fb = result["fusion_block"]  # MSSF-PointPillars' first FusionBlock on its captured input
    assert [r["precision"] for r in fb] == ["float32", "bf16 autocast"] and "error" not in fb[0], fb
    assert fb[0]["voxels"] > 0 and fb[0]["fwd_ms"] > 0 and fb[0]["fwd_bwd_ms"] > 0 and fb[0]["max_abs_diff_vs_fp32"] == 0
    assert 0 < fb[1]["max_abs_diff_vs_fp32"] < 0.5
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
    md = (out / "gpu_check.md").read_text()
    assert "## (e) The shipped mmdet3d config" in md
    assert "## (b) Sampling core" in md and "## (a) Tests on the device" in md
    assert "## (c) MSDFF" in md and "## (c) A FusionBlock" in md and "## (d) Each detector" in md and "pointpillars" in md
    print(f"dry run of the device command: {seconds:.0f} s")




def test_every_stage_is_cut_to_the_deadline_and_rows_past_it_are_listed(tmp_path):
    """--deadline-s 0: no stage measures past its start (the rows say skipped), the run still writes its report."""
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples"), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--smoke", "--device", "cpu",
                        "--skip-install", "--skip-tests", "--repeats", "1", "--deadline-s", "0", "--out", str(tmp_path)],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    result = json.loads((tmp_path / "gpu_check.json").read_text())
    assert result["stage"] == "done", (r.stdout + r.stderr)[-2000:]
    assert all(row.get("skipped") for row in result["msdff"]) and all(row.get("skipped") for row in result["fusion_block"])
    assert all(row["error"].startswith("skipped: past") for row in result["detectors"])
    assert result["sampling"] and all("skipped" in str(row["grid_fwd_ms"]) for row in result["sampling"])
    mm = result["mmdet3d"]
    assert "skipped" in mm or mm["error"].startswith("timed out after 1 s"), mm
    assert r.returncode == 1  # the skipped detectors count as failures of the check


def test_the_watchdog_stops_the_run_and_says_where(tmp_path):
    code = ("import sys, time; sys.path.insert(0, sys.argv[1]); import gpu_check, _gpu_report; "
            "r = _gpu_report.Report(sys.argv[2], stage='detectors', stages={}); r.row('detectors')({'detector': 'x'}); "
            "gpu_check._watchdog(r, 0.5); time.sleep(60)")
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", code, str(REPO / "benchmarks"), str(tmp_path)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 3 and time.perf_counter() - t0 < 50, r.stderr[-2000:]
    result = json.loads((tmp_path / "gpu_check.json").read_text())
    assert result["detectors"] == [{"detector": "x"}]  # what was measured before it stays
    assert result["stopped"].startswith("watchdog: 0 s passed during stage detectors")
    assert "**Stopped:** watchdog" in (tmp_path / "gpu_check.md").read_text()


def test_gpu_check_refuses_a_missing_gpu_clearly(tmp_path):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples")]))
    r = subprocess.run([sys.executable, str(REPO / "benchmarks" / "gpu_check.py"), "--skip-install", "--out",
                        str(tmp_path)], cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2
    assert "sees no CUDA GPU" in r.stderr and "--smoke --device cpu" in r.stderr
