"""One-command device check: tests on the GPU, the MSDFF benchmark on the GPU, a training step per detector.

Run on a GPU machine from the repository root (``make gpu-check``)::

    python benchmarks/gpu_check.py [--out outputs/gpu_check] [--skip-install] [--mmcv-src mmcv-2.1.0.tar.gz]

From a bare machine it first makes sure the packages it needs import (torch with CUDA, einops,
numpy, pytest, spconv for the GPU's CUDA version, tqdm, pillow): missing ones are installed with pip
(``spconv-cu1xx`` matching ``torch.version.cuda``), or, with ``--skip-install`` or when pip fails,
named in the report. Then, each stage timed and bounded so the whole finishes in under 10 minutes
on one modern GPU (8 when nothing needs installing):

1. ``pytest`` on the device-parametrised tests (``tests/test_devices.py``, the fast-vs-reference tests
   of ``tests/test_fusion.py``, ``tests/test_msdff.py``, ``tests/functional/test_sampling.py`` and the
   sampling op's Triton-vs-grid check (``tests/functional/test_sampling_op.py``); the
   ``device`` fixture adds ``cuda``), the host-synchronisation count, the pinned-memory test, the
   distributed/CLI option tests (``-k "cuda or sync or pin or runtime or env"``) - pass/fail counts and
   the failures' names;
2. the MSDFF benchmark on VoD shapes (one 1216 x 1952 camera, FPN strides 4-64 with 256 channels,
   8 heads, 4 points, 5 levels, E = 64): the reference formulation (``method="reference"``,
   ``value_projection="before_sampling"``: ``value_proj`` on every pixel + ``grid_sample``, Deformable
   DETR's) against ours (``method="auto"``), forward and forward+backward, float32 and bfloat16
   autocast, N = 2,500 / 8,000 / 40,000 voxels; CUDA-event timing (median of repeats after a
   warm-up), peak memory (``torch.cuda.max_memory_allocated``), the output difference;
2b. the sampling core at VoD shapes (N = 2,500 / 8,000 / 20,000, 4-5 FPN levels of 1936 x 1216, 8 heads,
   4 points, d = 32 and 256, float32 and bfloat16): the sampling op's Triton kernels, the grid path and
   mmcv's ``MultiScaleDeformableAttnFunction`` where its compiled ops import (else, with ``--mmcv-src``,
   mmcv's CUDA op built alone from its source archive, ``benchmarks/_mmcv_build.py``); forward, forward +
   backward, peak memory, outputs against the grid path's (``benchmarks/_sampling_stage.py``);
3. one training step (forward + backward + AdamW step) of each example detector (VoD paper preset,
   n = 2 MSDFF blocks) on a VoD-sized synthetic frame (2,500 radar points, 1216 x 1936 image): median
   step time, peak memory; and the same step under bf16 and fp16 autocast (whether spconv's CUDA
   kernels take them is what this answers);
4. the shipped mmdetection3d config (MSSF-PointPillars, View-of-Delft) trained 20 iterations through
   ``python -m mssf_examples.mmdet3d train --iters 20`` on a generated VoD tree: mmengine's time per
   iteration (``benchmarks/_framework_stage.py``; reported as not run, with the reason, where mmdet3d or an
   mmcv with CUDA ops is missing).

Writes ``<out>/gpu_check.json`` and ``<out>/gpu_check.md`` (GPU, driver, torch, CUDA, spconv
versions; the tables). ``--smoke`` runs every stage at toy sizes on ``--device cpu`` (the test suite
runs it so that the script is known to work on machines without a GPU).

Stages 2 and 3 (the timed measurements) are in ``benchmarks/_gpu_stages.py``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

from _gpu_stages import detector_steps, msdff_benchmark  # benchmarks/ (the script's folder) is on sys.path
from _framework_stage import mmdet3d_training
from _sampling_stage import sampling_benchmark

REPO = Path(__file__).resolve().parents[1]

#: What each stage may take on a GPU (seconds); the whole stays under 10 minutes (8 without installs).
BUDGET_S = {"install": 150, "tests": 150, "msdff": 120, "detectors": 60, "sampling": 90, "mmdet3d": 90}


# --------------------------------------------------------------------------------------------------
# set-up
# --------------------------------------------------------------------------------------------------
def _spconv_wheel(cuda: Optional[str]) -> Optional[str]:
    """``spconv-cu1xx`` for a torch built with CUDA ``cuda`` (spconv publishes cu113 ... cu124 wheels)."""
    if not cuda:
        return None
    major, minor = (int(x) for x in cuda.split(".")[:2])
    tags = [(11, 3), (11, 4), (11, 6), (11, 7), (11, 8), (12, 0), (12, 1), (12, 4)]
    best = [t for t in tags if t[0] == major and t[1] <= minor] or [t for t in tags if t[0] <= major]
    if not best:
        return None
    a, b = best[-1]
    return f"spconv-cu{a}{b}"


def ensure_packages(install: bool, need_spconv: bool = True) -> Dict[str, str]:
    """Import every package the check needs; pip-install the missing ones when ``install``.

    Returns ``{package: version or "MISSING: why"}``; torch itself is never installed here (a CUDA
    build must match the driver: install it first, https://pytorch.org/get-started/locally/).
    """
    report: Dict[str, str] = {}
    try:
        import torch
    except ImportError:
        return {"torch": "MISSING: install a CUDA build of torch first (https://pytorch.org/get-started/locally/)"}
    report["torch"] = torch.__version__
    wanted = {"numpy": "numpy", "einops": "einops", "pytest": "pytest", "tqdm": "tqdm", "PIL": "pillow"}
    if need_spconv:
        wanted["spconv"] = _spconv_wheel(torch.version.cuda) or "spconv"
    for module, pip_name in wanted.items():
        try:
            report[pip_name] = getattr(importlib.import_module(module), "__version__", "present")
            continue
        except ImportError:
            pass
        if not install:
            report[pip_name] = f"MISSING: pip install {pip_name}"
            continue
        r = subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", pip_name], capture_output=True,
                           text=True, timeout=BUDGET_S["install"])
        try:
            importlib.invalidate_caches()
            report[pip_name] = getattr(importlib.import_module(module), "__version__", "installed")
        except ImportError:
            report[pip_name] = f"MISSING: pip install {pip_name} failed: {r.stderr.strip()[-300:]}"
    try:  # the library itself, from this checkout
        sys.path[:0] = [str(REPO / "src"), str(REPO / "examples")]
        import mssf_blocks

        report["mssf_blocks"] = getattr(mssf_blocks, "__version__", "present")
    except ImportError as exc:
        report["mssf_blocks"] = f"MISSING: {exc}"
    return report


def environment(device) -> Dict[str, object]:
    import torch

    env: Dict[str, object] = dict(python=platform.python_version(), torch=torch.__version__,
                                  cuda=torch.version.cuda, cudnn=torch.backends.cudnn.version(), device=str(device))
    if device.type == "cuda":
        p = torch.cuda.get_device_properties(device)
        env.update(gpu=p.name, gpu_memory_gib=round(p.total_memory / 2**30, 1), capability=f"{p.major}.{p.minor}",
                   bf16=torch.cuda.is_bf16_supported())
        try:
            env["driver"] = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                                           capture_output=True, text=True, timeout=20).stdout.strip()
        except (OSError, subprocess.TimeoutExpired):
            env["driver"] = None
    else:
        env["threads"] = torch.get_num_threads()
    try:
        import spconv

        env["spconv"] = spconv.__version__
    except ImportError:
        env["spconv"] = None
    return env


# --------------------------------------------------------------------------------------------------
# 1. tests
# --------------------------------------------------------------------------------------------------
def run_tests(smoke: bool) -> Dict[str, object]:
    """The device-parametrised tests in a subprocess (``-k cuda`` on a GPU; the CPU ones in smoke mode)."""
    files = ["tests/test_devices.py"] + ([] if smoke else ["tests/test_fusion.py", "tests/test_msdff.py",
                                                           "tests/functional/test_sampling.py",
                                                           "tests/functional/test_sampling_op.py",
                                                           "tests/examples/test_distributed.py"])
    select = "cpu and query_init" if smoke else "cuda or sync or pin or runtime or env"
    cmd = [sys.executable, "-m", "pytest", *files, "-q", "-p", "no:cacheprovider", "-k", select, "-rfEs"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples"),
                                                        os.environ.get("PYTHONPATH", "")]))
    t0 = time.perf_counter()
    try:
        r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=BUDGET_S["tests"])
        out, code = r.stdout + r.stderr, r.returncode
    except subprocess.TimeoutExpired as exc:
        out, code = (exc.stdout or "") if isinstance(exc.stdout, str) else "", "timeout"
    summary = [line for line in out.splitlines() if " passed" in line or " failed" in line or "error" in line.lower()]
    return dict(command=" ".join(cmd[1:]), returncode=code, seconds=time.perf_counter() - t0,
                summary=summary[-1] if summary else out[-500:],
                failures=[line for line in out.splitlines() if line.startswith(("FAILED", "ERROR"))],
                host_syncs=[line for line in out.splitlines() if "host syncs" in line])


# --------------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------------
def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e-2 else f"{v:.2f}"
    return str(v)


def _table(rows: List[Dict[str, object]], cols: List[str]) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def markdown(result: Dict[str, object]) -> str:
    env = result["environment"]
    parts = ["# GPU check", "", "Environment: " + ", ".join(f"{k} {v}" for k, v in env.items()), "",
             "Packages: " + ", ".join(f"{k} {v}" for k, v in result["packages"].items()), ""]
    t = result.get("tests")
    if t:
        parts += ["## Tests", "", f"`{t['command']}`: {t['summary']} (exit {t['returncode']}, {t['seconds']:.0f} s)", ""]
        parts += [f"- {f}" for f in t["failures"]] + [f"- {s}" for s in t["host_syncs"]] + [""]
    if result.get("msdff"):
        parts += ["## MSDFF, reference / ours (ratio > 1: ours faster)", "",
                  _table(result["msdff"], ["N", "precision", "fwd_ref_ms", "fwd_ours_ms", "fwd_ratio", "fwd_bwd_ref_ms",
                                           "fwd_bwd_ours_ms", "fwd_bwd_ratio", "fwd_bwd_ref_MiB", "fwd_bwd_ours_MiB",
                                           "max_abs_diff"]), ""]
    if result.get("sampling"):
        parts += ["## Sampling core: Triton op, grid path, mmcv's op (fwd+bwd ratio > 1: Triton faster)", "",
                  _table(result["sampling"], ["levels", "d", "dtype", "N", "grid_fwd_ms", "triton_fwd_ms", "mmcv_fwd_ms",
                                              "grid_fwd_bwd_ms", "triton_fwd_bwd_ms", "mmcv_fwd_bwd_ms",
                                              "fwd_bwd_ratio_grid_over_triton", "grid_MiB", "triton_MiB", "mmcv_MiB",
                                              "triton_max_abs_diff", "mmcv_max_abs_diff"]), ""]
    if result.get("detectors"):
        parts += ["## One training step per detector (n = 2 MSDFF blocks)", "",
                  _table(result["detectors"], ["detector", "step_ms", "peak_MiB", "loss_finite", "bf16_step_ms",
                                               "bf16_loss_finite", "fp16_step_ms", "fp16_loss_finite", "error"]), ""]
    if result.get("mmdet3d"):
        parts += ["## The shipped mmdet3d config, trained through our entry", "",
                  _table([result["mmdet3d"]], ["config", "iters", "iter_s", "loss", "loss_finite", "wall_s", "skipped",
                                               "error"]), ""]
    parts += [f"Total {result['seconds']:.0f} s."]
    return "\n".join(parts) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "gpu_check")
    ap.add_argument("--device", default="cuda", help="cuda (default), cuda:N, or cpu (with --smoke)")
    ap.add_argument("--smoke", action="store_true", help="toy sizes (CPU smoke test of this script)")
    ap.add_argument("--skip-install", action="store_true", help="do not pip-install missing packages, report them")
    ap.add_argument("--skip-tests", action="store_true")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats (default 5; 2 with --smoke)")
    ap.add_argument("--mmcv-src", type=Path, default=os.environ.get("MSSF_MMCV_SRC") or None,
                    help="an mmcv source archive (e.g. mmcv-2.1.0.tar.gz) or tree: where mmcv's compiled ops do not "
                         "import, stage 2b builds mmcv's deformable-attention CUDA op from it with nvcc, for the "
                         "comparison (default: $MSSF_MMCV_SRC)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    try:  # a machine without a GPU is told so at once, before any install
        import torch

        if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
            print(f"gpu_check: --device {args.device}: torch {torch.__version__} sees no CUDA GPU "
                  f"(torch.version.cuda = {torch.version.cuda}); install a CUDA build of torch, or run --smoke "
                  f"--device cpu", file=sys.stderr)
            return 2
    except ImportError:
        pass  # reported by ensure_packages
    packages = ensure_packages(install=not args.skip_install)
    missing = {k: v for k, v in packages.items() if str(v).startswith("MISSING")}
    if "torch" in missing or "mssf_blocks" in missing:
        print("gpu_check: cannot start: " + "; ".join(f"{k}: {v}" for k, v in missing.items()), file=sys.stderr)
        return 2
    import torch

    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print(f"gpu_check: --device {args.device}: torch {torch.__version__} sees no CUDA GPU "
              f"(torch.version.cuda = {torch.version.cuda}); install a CUDA build of torch, or run --smoke "
              f"--device cpu", file=sys.stderr)
        return 2
    if device.type == "cpu" and not args.smoke:
        print("gpu_check: --device cpu only with --smoke (the figures are for GPUs)", file=sys.stderr)
        return 2
    repeats = args.repeats or (2 if args.smoke else 5)
    result: Dict[str, object] = dict(environment=environment(device), packages=packages, smoke=args.smoke)
    print(f"gpu_check on {result['environment']}", flush=True)
    if not args.skip_tests:
        print("1/4 tests", flush=True)
        result["tests"] = run_tests(args.smoke)
        print(f"  {result['tests']['summary']}", flush=True)
    print("2/4 MSDFF benchmark", flush=True)
    result["msdff"] = msdff_benchmark(device, args.smoke, repeats)
    print("2b/4 sampling core: Triton op / grid path / mmcv", flush=True)
    result["sampling"] = sampling_benchmark(device, args.smoke, repeats, BUDGET_S["sampling"], args.mmcv_src,
                                            args.out / "mmcv_build")
    if "spconv" in missing:
        result["detectors"] = [dict(detector="all", error=packages["spconv"])]
    else:
        print("3/4 one training step per detector", flush=True)
        result["detectors"] = detector_steps(device, args.smoke, repeats)
    print("4/4 the shipped mmdet3d config, trained through python -m mssf_examples.mmdet3d", flush=True)
    result["mmdet3d"] = mmdet3d_training(device, args.smoke, timeout_s=300 if args.smoke else BUDGET_S["mmdet3d"])
    print(f"  {result['mmdet3d']}", flush=True)
    result["seconds"] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gpu_check.json").write_text(json.dumps(result, indent=1, default=str))
    (args.out / "gpu_check.md").write_text(markdown(result))
    print(f"wrote {args.out / 'gpu_check.json'} and {args.out / 'gpu_check.md'} ({result['seconds']:.0f} s)")
    failed = result.get("tests", {}).get("returncode", 0) not in (0, 5)  # 5: nothing selected
    failed = failed or "error" in result["mmdet3d"]
    return 1 if failed or any("error" in r for r in result["detectors"]) else 0


if __name__ == "__main__":
    sys.exit(main())
