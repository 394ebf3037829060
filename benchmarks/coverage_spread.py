"""Measurement: how far a sample's coverage strays from its running value in correct training.

The collapse warnings of the projector (``mssf_blocks.checks.coverage``, docs/conventions.md "Common
mistakes") fire when a sample's in-image fraction or centroid fraction falls below ``COLLAPSE_RATIO``
times its running value. This script trains the CLI's detector on a tree of generated VoD-like scenes
(augmentation on: flips, rotations +-pi/4, scaling) with correct geometry, records every sample's
fraction and the running value it was compared with, and prints per (kind, stride) the smallest and
largest ratio and how many samples fell below 0.25 / 0.5 of the running value. A threshold is sound when
correct training never crosses it.

Usage: ``python benchmarks/coverage_spread.py [--scenes 24] [--steps 24] [--detector pointpillars]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples"))

from mssf_blocks.checks import coverage as rc  # noqa: E402
from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.data.kitti_export import write_vod_tree  # noqa: E402
from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--steps", type=int, default=24)
    ap.add_argument("--detector", default="pointpillars")
    ap.add_argument("--fusion-blocks", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(1)

    records = {}  # (kind, stride) -> [(fraction, running mean)] after the warm-up
    original = rc.RunningCoverage.observe

    def observe(self, kind, stride, hits, totals, skip=()):
        for hit, total in zip(hits, totals):
            seen, mean = self.running(kind, stride)
            if total >= rc.MIN_SAMPLE_VOXELS and seen >= rc.WARMUP_SAMPLES:
                records.setdefault((kind, tuple(stride)), []).append((hit / total, mean))
            original(self, kind, stride, [hit], [total])

    rc.RunningCoverage.observe = observe
    with tempfile.TemporaryDirectory() as tmp:
        cfg = SceneConfig(image_size=(128, 204))
        train = [SyntheticDataset("train", args.scenes, cfg, seed=5)[i] for i in range(args.scenes)]
        write_vod_tree(Path(tmp) / "vod", {"train": train})
        code = cli.main(["train", "--dataset", "vod", "--data-root", str(Path(tmp) / "vod"), "--preset", "tiny",
                         "--detector", args.detector, "--steps", str(args.steps), "--batch-size", "2",
                         "--threads", "1", "--no-progress", "--fusion-blocks", str(args.fusion_blocks),
                         "--out", str(Path(tmp) / "out")])
    rc.RunningCoverage.observe = original
    print(f"exit {code}; {args.detector}, {args.scenes} scenes, {args.steps} steps of 2, augmentation on")
    print("| kind | stride | samples | mean fraction | min ratio | max ratio | below 0.25 | below 0.5 |")
    print("|---|---|---|---|---|---|---|---|")
    for (kind, stride), rows in sorted(records.items()):
        ratios = [f / m for f, m in rows if m > 0]
        print(f"| {kind} | {stride} | {len(rows)} | {statistics.mean(f for f, _ in rows):.3f} | "
              f"{min(ratios):.2f} | {max(ratios):.2f} | {sum(r < 0.25 for r in ratios)} | "
              f"{sum(r < 0.5 for r in ratios)} |")


if __name__ == "__main__":
    main()
