"""Benchmark: CPU cost of the geometry sanity checks (issue 33) in a detector forward.

The frame of ``benchmarks/detectors.py`` (2,500 radar points in the camera's view, one 1216 x 1936
camera, precomputed FPN levels), each detector with two MSDFF fusion blocks, eval mode, one thread.
Two figures per detector, both from this one process:

* ``checks ms``: the process CPU time spent inside the checks themselves (projection and centroid
  coverage, level sizes, the metric grid, the spconv index range, and issue 42's first-call checks: the
  raw points' projection, points in voxels, ``image_size`` too small, ``points_to_sensor`` against its
  inverse and none: the frame carries an identity ``points_to_sensor`` so that this one runs), summed
  over a forward, median
  forward CPU time beside it and the share (target: at most 2 % of the forward);
* ``on / off``: forward CPU time with the data-reading checks on (the CPU default) and off
  (``set_geometry_checks(False)``) in interleaved rounds, the ratio of the medians and the per-round
  spread (on a shared machine the spread is the noise floor; the shape-only checks stay on in both).

Usage: ``python benchmarks/geometry_checks.py [--rounds 7] [--detectors second pointpillars]``
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from detectors import vod_frame  # noqa: E402  (this folder)
from mssf_blocks import blocks as _blocks  # noqa: E402
from mssf_blocks import samplers as _fusion  # noqa: E402
from mssf_blocks import geometry as _geometry  # noqa: E402
from mssf_examples.models.detectors import build_detector  # noqa: E402
from mssf_examples.models.presets import VOD  # noqa: E402

CHECKS = ("check_projection_coverage", "check_centroid_coverage", "check_level_sizes", "check_grid",
          "check_indices_in_shape", "project_raw", "check_points_in_voxels", "check_points_to_sensor",
          "check_image_size_small")


def _timed_checks(spent):
    """Wrap the checks where the blocks call them; returns the originals to restore."""
    originals = []
    for mod in (_geometry, _blocks, _fusion):
        for name in CHECKS:
            if hasattr(mod, name):
                orig = getattr(mod, name)

                def wrapper(*a, _orig=orig, _name=name, **k):
                    t0 = time.process_time()
                    try:
                        return _orig(*a, **k)
                    finally:
                        spent[_name] += time.process_time() - t0

                setattr(mod, name, wrapper)
                originals.append((mod, name, orig))
    return originals


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--detectors", nargs="+", default=["second", "pointpillars"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    frame = vod_frame(2500, channels_last=True)
    frame = dataclasses.replace(frame, points_to_sensor=torch.eye(4)[None])  # (runs the points_to_sensor check)
    print(f"{'detector':<13} {'forward ms':>10} {'checks ms':>9} {'share':>7} | {'on ms':>7} {'off ms':>7} "
          f"{'on/off':>6} {'rounds':>11}")
    for name in args.detectors:
        torch.manual_seed(0)
        model = build_detector(name, VOD, num_fusion_blocks=2, fusion="msdff", image_features="precomputed").eval()
        spent = {n: 0.0 for n in CHECKS}
        on, off = [], []
        with torch.no_grad():
            model(frame)  # warm-up
            originals = _timed_checks(spent)
            try:
                for r in range(args.rounds):
                    order = ((None, on), (False, off)) if r % 2 == 0 else ((False, off), (None, on))
                    for flag, acc in order:
                        _geometry.set_geometry_checks(flag)
                        t0 = time.process_time()
                        model(frame)
                        acc.append(time.process_time() - t0)
            finally:
                _geometry.set_geometry_checks(None)
                for mod, n, orig in originals:
                    setattr(mod, n, orig)
        checks = sum(spent.values()) / args.rounds  # (the "off" forwards spend ~0 in the data checks)
        fwd = statistics.median(on)
        per = [a / b for a, b in zip(on, off)]
        print(f"{name:<13} {fwd * 1e3:>10.1f} {checks * 1e3:>9.3f} {100 * checks / fwd:>6.3f}% | "
              f"{fwd * 1e3:>7.1f} {statistics.median(off) * 1e3:>7.1f} {fwd / statistics.median(off):>6.3f} "
              f"{min(per):>5.2f}-{max(per):.2f}")
        print("    per check (ms per forward): " + ", ".join(
            f"{n} {spent[n] / args.rounds * 1e3:.3f}" for n in CHECKS if spent[n] > 0))


if __name__ == "__main__":
    main()
