"""Compiled training on the CPU: MSDFF's sampling through the sampling op or the static grid plan.

Measures the choice ``plan_costs.COMPILED_TRAINING["cpu"]``: one training step (forward + backward) of
``benchmarks/compile.py``'s ``FusionBlock(MSDFF)`` frame, compiled with ``torch.compile(fullgraph=True,
dynamic=True)`` (inductor) once per choice, and eager, timed in interleaved rounds in one process (the
machine is shared: interleaving keeps the ratios fair), medians reported with each first call.

Run: ``python benchmarks/compile_training.py [--rounds 9] [--voxels 4100] [--threads 1]``.
"""

from __future__ import annotations

import argparse
import copy
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import compile as bench  # noqa: E402

from mssf_blocks import torch_versions as _compat  # noqa: E402
from mssf_blocks.functional import plan_costs  # noqa: E402

CHOICES = ("op", "grid")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--voxels", type=int, default=4100)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    _compat.require("compile_dynamic", "benchmarks/compile_training.py")
    torch.set_num_threads(args.threads)
    first, frame = bench._frame(2000, seed=0), bench._frame(args.voxels, seed=1)
    base, run = bench._cases()["FusionBlock(MSDFF)"]()
    base.train(True)
    compiled = torch.compile(run, fullgraph=True, dynamic=True)  # (one cache entry per choice: the table is guarded)
    mods = {k: copy.deepcopy(base) for k in (*CHOICES, "eager")}
    saved = plan_costs.COMPILED_TRAINING.get("cpu")
    firsts = {}
    try:
        for k in CHOICES:
            plan_costs.COMPILED_TRAINING["cpu"] = k
            t0 = time.perf_counter()
            bench._call(compiled, mods[k], first, True)
            firsts[k] = time.perf_counter() - t0
            bench._call(compiled, mods[k], frame, True)  # (warm-up at the timed size)
        bench._call(run, mods["eager"], frame, True)
        times = {k: [] for k in mods}
        for _ in range(args.rounds):
            for k in mods:
                if k != "eager":
                    plan_costs.COMPILED_TRAINING["cpu"] = k
                t0 = time.perf_counter()
                bench._call(run if k == "eager" else compiled, mods[k], frame, True)
                times[k].append(time.perf_counter() - t0)
    finally:
        plan_costs.COMPILED_TRAINING["cpu"] = saved
    med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    for k in CHOICES:
        print(f"{k:5s} first call {firsts[k]:6.1f} s  step {med[k]:7.1f} ms  eager/compiled {med['eager'] / med[k]:.2f}")
    print(f"eager            step {med['eager']:7.1f} ms  ({args.rounds} interleaved rounds, N = {args.voxels})")


if __name__ == "__main__":
    main()
