"""One-command device check: the CUDA tests, the sampling op, MSDFF and a FusionBlock, each detector.

On the GPU machine this project is lent (bare, no network: docs/gpus.md, "The device check"), from the
repository root, with the bundle built here by ``make gpu-bundle`` carried along::

    python3 benchmarks/gpu_check.py --bundle .carry/gpu_bundle --out $OUT/gpu_check

``--bundle`` verifies the bundle's files against its manifest and installs them offline into ``--site``
(default ``$TMPDIR/mssf_gpu_site``: pip ``--no-index`` for the wheels, the repacked ``tar.xz`` unpacked),
put first on ``sys.path`` and ``PYTHONPATH``; nothing is fetched (``benchmarks/_bundle.py``). Without
``--bundle`` (``make gpu-check`` on a machine with network) missing packages are pip-installed as before
(``numpy``, ``einops``, ``pytest``, ``tqdm``, ``pillow``, ``spconv-cu1xx`` for torch's CUDA), or with
``--skip-install`` named in the report.

The stages, in the order of what a GPU user depends on most, each bounded by its budget
(:data:`BUDGET_S`, cut to what is left of ``--deadline-s``; rows past it are listed as skipped) so that the
first minutes answer the most; a watchdog ends the run 25 s after the deadline:

a. ``pytest`` on the CUDA-parametrised tests (``tests/test_devices.py``, the fast-vs-reference tests of
   ``tests/samplers/test_sff.py``, ``tests/samplers/test_msdff.py`` and their shared block checks
   (``tests/samplers/test_sff_tester.py``, ``test_msdff_tester.py``), ``tests/functional/test_sampling.py``, the sampling
   op's Triton-vs-grid-vs-float64 checks in ``tests/functional/test_sampling_op.py``, the distributed
   options: ``-k "cuda or sync or pin or runtime or env"``), its log written to ``<out>/tests.log`` as it
   runs; meanwhile, with an mmcv source archive (the bundle's, or ``--mmcv-src``), nvcc builds mmcv's
   deformable-attention op in the background (``_mmcv_build.py``);
b. the sampling core at VoD shapes: Triton kernels vs the grid path vs mmcv's op, forward and forward +
   backward, fp32 and bf16, N = 2,500 / 8,000 / 20,000, peak memory (``_sampling_stage.py``);
c. MSDFF, reference formulation vs ours, at the paper's width (N = 2,500 / 8,000 / 40,000), and
   MSSF-PointPillars' first FusionBlock on its VoD-frame input (``_gpu_stages.py``, ``_fusion_stage.py``);
d. per example detector at a VoD frame (1216 x 1936 image, 2,500 radar points), MSSF-PointPillars first
   (pure torch), then SECOND, CenterPoint, VoxelNeXt (spconv): one training step and the inference
   latency, float32 and bf16 autocast (training also fp16), peak memory;
e. the shipped mmdetection3d config, 20 iterations, where mmdet3d with mmcv's CUDA ops imports
   (``_framework_stage.py``; the bare GPU machine has neither: "not run").

Every row is written to ``<out>/gpu_check.json`` and ``gpu_check.md`` as soon as it is measured
(``_gpu_report.py``), so a run stopped at its limit still returns what it measured. ``--smoke`` runs every
stage at toy sizes on ``--device cpu``; the test suite runs it from a copy of the tracked files with a
stand-in bundle and no network (``tests/project/test_gpu_check.py``), so the command is known to work before a
GPU runs it.
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Dict, Optional, Sequence

import _bundle  # benchmarks/ (the script's folder) is on sys.path
import _mmcv_build
from _framework_stage import mmdet3d_training
from _fusion_stage import fusion_block_benchmark
from _gpu_report import Report
from _gpu_stages import detector_steps, msdff_benchmark
from _sampling_stage import sampling_benchmark

REPO = Path(__file__).resolve().parents[1]

#: What each stage may take on the H200 (seconds), cut to what is left of ``--deadline-s`` (default 510 s: the
#: device call's limit is 600 s, the machine's start and the transfers are not counted in it). The mmcv build
#: (background, during the tests) may take ``mmcv_build`` more before stage b gives up on it.
BUDGET_S = {"install": 150, "tests": 150, "mmcv_build": 120, "sampling": 100, "msdff": 60, "fusion_block": 30,
            "detectors": 120, "mmdet3d": 90}
DEADLINE_S = 510.0


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


def ensure_packages(install: bool, need_spconv: bool = True, extra: Sequence[str] = ()) -> Dict[str, str]:
    """Import every package the check needs; pip-install the missing ones when ``install``.

    ``extra``: more modules to report (the bundle's). Returns ``{package: version or "MISSING: why"}``; torch itself is never installed here (a CUDA
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
    wanted.update({m: m for m in extra if m not in wanted})
    for module, pip_name in wanted.items():
        try:
            report[pip_name] = getattr(importlib.import_module(module), "__version__", "present")
            continue
        except Exception as exc:  # noqa: BLE001 - ImportError, or an OSError of a compiled library (spconv's)
            why = f"{type(exc).__name__}: {str(exc)[:200]}"
        if not install:
            report[pip_name] = f"MISSING: {why}"
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
    except Exception:  # noqa: BLE001 - ImportError, or an OSError of its compiled libraries
        env["spconv"] = None
    import mssf_blocks

    env["mssf_blocks"] = str(Path(mssf_blocks.__file__).parent)  # (this checkout's, not an installed copy)
    return env


# --------------------------------------------------------------------------------------------------
# 1. tests
# --------------------------------------------------------------------------------------------------
def run_tests(smoke: bool, log: Path, timeout_s: float) -> Dict[str, object]:
    """The device-parametrised tests in a subprocess (``-k cuda`` on a GPU; the CPU ones in smoke mode),
    their output written to ``log`` as they run (a run stopped at its limit keeps what passed)."""
    files = ["tests/test_devices.py"] + ([] if smoke else ["tests/samplers/test_sff.py", "tests/samplers/test_msdff.py",
                                                           # the fast-vs-reference checks of the shared block tester
                                                           "tests/samplers/test_sff_tester.py",
                                                           "tests/samplers/test_msdff_tester.py",
                                                           "tests/functional/test_sampling.py",
                                                           "tests/functional/test_sampling_op.py",
                                                           "tests/examples/training/test_distributed.py"])
    select = "cpu and query_init" if smoke else "cuda or sync or pin or runtime or env"
    # (-v: one line per test, so a log cut at the time limit still says which passed and which failed)
    cmd = [sys.executable, "-m", "pytest", *files, "-v", "-p", "no:cacheprovider", "-k", select, "-rfEs"]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples"),
                                                        os.environ.get("PYTHONPATH", "")]))
    t0 = time.perf_counter()
    with open(log, "w") as f:
        try:
            code = subprocess.run(cmd, cwd=REPO, env=env, stdout=f, stderr=subprocess.STDOUT, timeout=timeout_s).returncode
        except subprocess.TimeoutExpired:
            code = f"timeout after {timeout_s:.0f} s"
    out = Path(log).read_text(errors="replace")
    summary = [line for line in out.splitlines() if " passed" in line or " failed" in line or "error" in line.lower()]
    return dict(command=" ".join(cmd[1:]), returncode=code, seconds=time.perf_counter() - t0,
                summary=summary[-1] if summary else out[-500:],
                failures=[line for line in out.splitlines() if line.startswith(("FAILED", "ERROR"))],
                host_syncs=[line for line in out.splitlines() if "host syncs" in line])


# --------------------------------------------------------------------------------------------------
# the run
# --------------------------------------------------------------------------------------------------
class _Tee:
    """stdout also into ``<out>/gpu_check.log`` (the device call returns only the output's tail)."""

    def __init__(self, stream, path: Path) -> None:
        self.stream, self.file = stream, open(path, "a", buffering=1)

    def write(self, text):
        self.stream.write(text)
        self.file.write(text)
        return len(text)

    def flush(self):
        self.stream.flush()
        self.file.flush()


def _watchdog(report: Report, after_s: float) -> threading.Timer:
    """Ends the process ``after_s`` seconds from now, noting in the report which stage it stopped."""
    def stop():
        report.set("stopped", f"watchdog: {after_s:.0f} s passed during stage {report.result.get('stage')}; "
                              "the rows above are what it measured")
        print(f"gpu_check: {report.result['stopped']}", flush=True)
        os._exit(3)

    timer = threading.Timer(after_s, stop)
    timer.daemon = True
    timer.start()
    return timer


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "gpu_check")
    ap.add_argument("--device", default="cuda", help="cuda (default), cuda:N, or cpu (with --smoke)")
    ap.add_argument("--smoke", action="store_true", help="toy sizes (CPU smoke test of this script)")
    ap.add_argument("--bundle", type=Path, default=None,
                    help="a bundle from benchmarks/gpu_bundle.py (`make gpu-bundle`): installed offline into --site "
                         "first; implies --skip-install")
    ap.add_argument("--site", type=Path, default=None,
                    help="where --bundle is installed (default: $TMPDIR/mssf_gpu_site); put first on the path")
    ap.add_argument("--skip-install", action="store_true", help="do not pip-install missing packages, report them")
    ap.add_argument("--skip-tests", action="store_true")
    ap.add_argument("--repeats", type=int, default=None, help="timed repeats (default 5; 2 with --smoke)")
    ap.add_argument("--deadline-s", type=float, default=None,
                    help=f"the whole run's time budget in seconds (default {DEADLINE_S:.0f} on a GPU, none with "
                         "--smoke); stages are cut to it, a watchdog ends the run 25 s after it")
    ap.add_argument("--mmcv-src", type=Path, default=os.environ.get("MSSF_MMCV_SRC") or None,
                    help="an mmcv source archive (e.g. mmcv-2.1.0.tar.gz) or tree: where mmcv's compiled ops do not "
                         "import, stage b builds mmcv's deformable-attention CUDA op from it with nvcc, for the "
                         "comparison (default: the bundle's, else $MSSF_MMCV_SRC)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    deadline_s = args.deadline_s if args.deadline_s is not None else (None if args.smoke else DEADLINE_S)
    try:  # a machine without a GPU is told so at once, before any install
        import torch

        if torch.device(args.device).type == "cuda" and not torch.cuda.is_available():
            print(f"gpu_check: --device {args.device}: torch {torch.__version__} sees no CUDA GPU "
                  f"(torch.version.cuda = {torch.version.cuda}); install a CUDA build of torch, or run --smoke "
                  f"--device cpu", file=sys.stderr)
            return 2
        if torch.device(args.device).type == "cpu" and not args.smoke:
            print("gpu_check: --device cpu only with --smoke (the figures are for GPUs)", file=sys.stderr)
            return 2
    except ImportError:
        pass  # reported by ensure_packages
    args.out.mkdir(parents=True, exist_ok=True)
    sys.stdout = _Tee(sys.stdout, args.out / "gpu_check.log")
    report = Report(args.out, smoke=args.smoke, stage="install", stages={})
    if deadline_s is not None:
        _watchdog(report, deadline_s + 25 - (time.perf_counter() - t0))

    def stage_deadline(name: str) -> float:
        """perf_counter() by which stage ``name`` should be done (its budget, cut to the whole's)."""
        end = time.perf_counter() + BUDGET_S[name]
        return end if deadline_s is None else min(end, t0 + deadline_s)

    def begin(name: str) -> float:
        report.result["stages"][name] = f"started at {time.perf_counter() - t0:.0f} s"
        report.set("stage", name)
        print(f"[{time.perf_counter() - t0:5.0f} s] stage {name}", flush=True)
        return stage_deadline(name)

    def end(name: str) -> None:
        report.result["stages"][name] += f", done at {time.perf_counter() - t0:.0f} s"
        report.save()

    mmcv_src, extra = args.mmcv_src, []
    if args.bundle is not None:
        begin("install")
        site = args.site or Path(tempfile.gettempdir()) / "mssf_gpu_site"
        try:
            info = _bundle.install(args.bundle, site, timeout_s=BUDGET_S["install"])
            _bundle.activate(site)
            mmcv_src = mmcv_src or info["archives"].get("mmcv_src")
            extra = [e["provides"] for e in info["installed"] if e.get("provides")]
        except _bundle.BundleError as exc:  # the stages that need what it holds say so; the others run
            info = dict(error=str(exc))
        report.set("bundle", info)
        print(f"  bundle: {info.get('error') or info['target']}", flush=True)
        end("install")
    packages = ensure_packages(install=not (args.skip_install or args.bundle), extra=extra)
    report.set("packages", packages)
    missing = {k: v for k, v in packages.items() if str(v).startswith("MISSING")}
    if "torch" in missing or "mssf_blocks" in missing:
        print("gpu_check: cannot start: " + "; ".join(f"{k}: {v}" for k, v in missing.items()), file=sys.stderr)
        return 2
    import torch

    device = torch.device(args.device)
    repeats = args.repeats or (2 if args.smoke else 5)
    report.set("environment", environment(device))
    print(f"gpu_check on {report.result['environment']}", flush=True)
    build_dir = Path(tempfile.mkdtemp(prefix="mssf_mmcv_build_"))
    builder, build_t0, mmcv_why = None, time.perf_counter(), None
    if device.type == "cuda" and mmcv_src is not None and not _mmcv_ops_import():
        builder = _mmcv_build.start_build(mmcv_src, build_dir, args.out / "mmcv_build.log")
        report.result["stages"]["mmcv_build"] = f"started at {build_t0 - t0:.0f} s (background, nvcc)"
    if not args.skip_tests:
        stop = begin("tests")
        report.set("tests", run_tests(args.smoke, args.out / "tests.log", max(stop - time.perf_counter(), 10)))
        print(f"  {report.result['tests']['summary']}", flush=True)
        end("tests")
    stop = begin("sampling")
    if builder is not None:  # nvcc has been compiling during the tests; give it what is left of its budget
        try:
            code = builder.wait(timeout=max(build_t0 + BUDGET_S["mmcv_build"] - time.perf_counter(), 1))
        except subprocess.TimeoutExpired:
            builder.kill()
            code = f"killed after {BUDGET_S['mmcv_build']} s"
        report.result["stages"]["mmcv_build"] += f", exit {code} at {time.perf_counter() - t0:.0f} s (mmcv_build.log)"
        if code != 0:  # (stage b would otherwise compile it again in this process, unbounded)
            mmcv_why = f"n/a (building mmcv's op from {mmcv_src}: exit {code}, see mmcv_build.log)"
        stop = stage_deadline("sampling")
    sampling_benchmark(device, args.smoke, repeats, max(stop - time.perf_counter(), 0), mmcv_src, build_dir,
                       on_row=report.row("sampling"), mmcv_unavailable=mmcv_why)
    end("sampling")
    msdff_benchmark(device, args.smoke, repeats, deadline=begin("msdff"), on_row=report.row("msdff"))
    end("msdff")
    fusion_block_benchmark(device, args.smoke, repeats, deadline=begin("fusion_block"), on_row=report.row("fusion_block"))
    end("fusion_block")
    detector_steps(device, args.smoke, repeats, deadline=begin("detectors"), on_row=report.row("detectors"))
    end("detectors")
    stop = begin("mmdet3d")
    report.set("mmdet3d", mmdet3d_training(device, args.smoke, timeout_s=300 if deadline_s is None else
                                           max(stop - time.perf_counter(), 1)))
    print(f"  {report.result['mmdet3d']}", flush=True)
    end("mmdet3d")
    report.result["stage"] = "done"
    report.set("seconds", time.perf_counter() - t0)
    print(f"wrote {args.out / 'gpu_check.json'} and {args.out / 'gpu_check.md'} ({report.result['seconds']:.0f} s)")
    result = report.result
    failed = result.get("tests", {}).get("returncode", 0) not in (0, 5)  # 5: nothing selected
    failed = failed or "error" in result["mmdet3d"] or "error" in result.get("bundle", {})
    return 1 if failed or any("error" in r for r in result.get("detectors", [])) else 0


def _mmcv_ops_import() -> bool:
    try:
        from mmcv.ops.multi_scale_deform_attn import ext_module  # noqa: F401
        return True
    except Exception:  # noqa: BLE001 - not installed, or a build without compiled ops
        return False


if __name__ == "__main__":
    sys.exit(main())
