"""Benchmark: demo training steps vs intra-op threads and OpenMP wait policy, idle and under load.

Measures what ``examples/mssf_examples/training/threads.py`` (the single home of the thread defaults of the
demo, the CLI and the tests) chose. For each combination of

* ``--threads`` (torch intra-op threads: 1 and 2),
* the OpenMP wait policy (libgomp's default, which spins before sleeping, and ``OMP_WAIT_POLICY=PASSIVE``;
  it must be set before torch is imported, so each case runs in a fresh subprocess),
* the load: none, or one competing process on ``--competitor-threads`` threads, started before and
  killed after the cases: ``--competitor matmul`` (a loop of 256 x 256 matmuls) or ``small-ops`` (a
  loop of small matmul + element-wise ops, like another demo or test run),

it times ``--steps`` image-branch pre-training steps of the demo (``examples/train_demo.py``'s default
configuration: ResNet-18 + FPN, 8 base channels, batch 8, 160 x 256 generated scenes) after one
warm-up step, and reports the median seconds per step. The machine's other load (``/proc/loadavg``)
is printed with each row: on a shared machine "no competitor" is not "idle".

Usage: ``python benchmarks/threads.py [--steps 3] [--competitor-threads 1]
[--threads 1 2] [--json out.json]`` (about 2-4 minutes on a 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# One case, run in a fresh interpreter so that the OpenMP environment is read at torch's import.
_CASE = r"""
import json, statistics, sys, time
sys.path.insert(0, {examples!r})
import torch
torch.set_num_threads({threads})
from mssf_examples.models.image_branch import ImageBranch
from mssf_examples.training.image_pretrain import pretrain_image_branch
from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset
ds = SyntheticDataset("train", 8, SceneConfig(), seed=0)
scenes = [ds[i] for i in range(len(ds))]
torch.manual_seed(0)
branch = ImageBranch(18, 8, 16, 4)
times = []
def timed(it):
    for i in it:
        t0 = time.perf_counter()
        yield i
        times.append(time.perf_counter() - t0)
pretrain_image_branch(branch, scenes, {steps} + 1, batch_size=8, progress=timed)
print(json.dumps(statistics.median(times[1:])))
"""

_COMPETITORS = {
    # a BLAS-bound job: large matmuls
    "matmul": "import torch\ntorch.set_num_threads({threads})\na = torch.randn(256, 256)\n"
              "while True:\n    a = torch.tanh(a @ a)\n",
    # a job like ours (another demo, a test run): many small ops, each an OpenMP parallel region
    "small-ops": "import torch\ntorch.set_num_threads({threads})\na = torch.randn(64, 2048)\nw = torch.randn(64, 64)\n"
                 "while True:\n    a = torch.relu(w @ a).mul_(0.5).add_(0.1)\n",
}


def run_case(threads: int, passive: bool, steps: int) -> float:
    env = dict(os.environ)
    env.pop("OMP_WAIT_POLICY", None)
    env.pop("OMP_NUM_THREADS", None)
    if passive:
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "src"), env.get("PYTHONPATH", "")])
    code = _CASE.format(examples=str(REPO / "examples"), threads=threads, steps=steps)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=3, help="timed steps per case (after one warm-up)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--competitor-threads", type=int, default=1)
    ap.add_argument("--competitor", choices=sorted(_COMPETITORS), default="matmul",
                    help="the competing job (its OpenMP wait policy is libgomp's default)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    rows = []
    print(f"{'load':<16} {'threads':>7} {'wait policy':<12} {'s/step':>8}   loadavg before")
    for load in ("none", f"{args.competitor} x{args.competitor_threads}"):
        competitor = None
        if load != "none":
            env = dict(os.environ, OMP_NUM_THREADS=str(args.competitor_threads))
            env.pop("OMP_WAIT_POLICY", None)
            code = _COMPETITORS[args.competitor].format(threads=args.competitor_threads)
            competitor = subprocess.Popen([sys.executable, "-c", code], env=env)
            time.sleep(2.0)  # let it start and reach its loop
        try:
            for threads in args.threads:
                for passive in (False, True):
                    loadavg = Path("/proc/loadavg").read_text().split()[0]
                    sec = run_case(threads, passive, args.steps)
                    policy = "PASSIVE" if passive else "default"
                    rows.append({"load": load, "threads": threads, "wait_policy": policy, "seconds_per_step": sec,
                                 "loadavg": float(loadavg)})
                    print(f"{load:<16} {threads:>7} {policy:<12} {sec:>8.3f}   {loadavg}", flush=True)
        finally:
            if competitor is not None:
                competitor.kill()
                competitor.wait()
    if args.json:
        args.json.write_text(json.dumps({"steps": args.steps, "competitor": args.competitor, "cpus": os.cpu_count(), "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
