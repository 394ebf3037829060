"""Measurement: the figures of the first-call consistency checks on correct inputs and on mistakes.

The checks of ``mssf_blocks.checks.first_call`` (docs/conventions.md, "Common mistakes") warn on one call,
without a warm-up, so their thresholds must hold on every correct frame. This script records, wherever
the projector runs the checks:

* ``points in voxels``: per sample, the fraction of its raw points on the grid whose voxel (at the
  voxels' stride) is one of its voxels (warning below 0.5);
* ``points_to_sensor``: per sample, the in-image fraction of its raw points with the matrix, and the best
  of the fractions with its inverse / without it (warning when the alternative is >= 1.5x and >= 0.15 more);
* ``image_size``: the share of the in-image raw projections in the top-left quarter of the image, the
  principal points (as fractions of ``image_size``) and how many more raw points project inside twice
  ``image_size`` than inside it (too large: a share >= 0.75 and every principal point in (0.125, 0.375];
  too small: >= 2x and every principal point in [0.75, 1.5)).

Correct inputs: the CLI's training on generated VoD-like scenes (augmentation on: flips, +-pi/4
rotations, scaling) for ``--detectors``, the demo detectors on the test fixture batch, the two real VoD
frames (VoD grid and the coarse 0.2 / 0.2 / 0.25 m grid, strides 1, 2, 4 built by spconv convolutions of
kernel 3, stride 2, padding 1, random augmentations with the correct ``points_to_sensor``).

Usage: ``python benchmarks/first_call_spread.py [--scenes 16] [--steps 12] [--detectors second pointpillars]``
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))

from mssf_blocks import SparseVoxels, VoxelCentroidProjector  # noqa: E402
from mssf_blocks.checks import first_call as cc  # noqa: E402
from mssf_blocks import geometry as _geometry  # noqa: E402
from mssf_blocks.checks.geometry import _relative_centre  # noqa: E402
from mssf_blocks.errors import MSSFGeometryWarning  # noqa: E402
from mssf_blocks.geometry import augmentation_matrix  # noqa: E402

COARSE = (0.2, 0.2, 0.25)
VOD_GRID = (0.05, 0.05, 0.125)
RANGE = (0.0, -25.6, -3.0, 51.2, 25.6, 2.0)


class Recorder:
    def __init__(self) -> None:
        self.rows = {"pv": [], "p2s": [], "quarter": []}
        self._orig = (cc.points_in_voxels, cc.sensor_fractions, _geometry.project_raw)

    def __enter__(self):
        piv, sf, pr = self._orig

        def points_in_voxels(*a, **k):
            on, hit = piv(*a, **k)
            for n, h in zip(on.tolist(), hit.tolist()):
                if n >= cc.MIN_POINTS:
                    self.rows["pv"].append((tuple(a[7]), h / n))
            return on, hit

        def sensor_fractions(*a, **k):
            n, mine, alts = sf(*a, **k)
            for b in range(len(n)):
                if n[b] >= cc.MIN_PROJECTED:
                    best = max(float(v[b]) for v in alts.values())
                    self.rows["p2s"].append((float(mine[b]), best))
            return n, mine, alts

        def project_raw(*a, **k):
            uv, inside = pr(*a, **k)
            pts = uv[inside]
            if pts.shape[0] >= 8:
                h, w = a[3]
                centre = _relative_centre(a[2], h, w)
                twice = int(((uv >= 0) & (uv <= 2)).all(-1).sum())
                self.rows["quarter"].append((float((pts <= 0.5).all(-1).double().mean()), float(centre.amin()),
                                             float(centre.amax()), twice / pts.shape[0]))
            return uv, inside

        cc.points_in_voxels, cc.sensor_fractions = points_in_voxels, sensor_fractions
        _geometry.project_raw = project_raw
        return self

    def __exit__(self, *exc):
        cc.points_in_voxels, cc.sensor_fractions, _geometry.project_raw = self._orig

    def report(self, name: str) -> None:
        pv = self.rows["pv"]
        strides = sorted({s for s, _ in pv})
        parts = [f"stride {s}: min {min(f for t, f in pv if t == s):.3f} ({sum(t == s for t, _ in pv)})"
                 for s in strides]
        p2s = self.rows["p2s"]
        ratio = [b / max(m, 1e-9) for m, b in p2s]
        gain = [b - m for m, b in p2s]
        warn = sum(b >= cc.INVERSE_RATIO * m and b - m >= cc.MIN_GAIN for m, b in p2s)
        q = self.rows["quarter"]
        quarter = (f"quarter share max {max(r[0] for r in q):.2f}, principal point {min(r[1] for r in q):.3f}-"
                   f"{max(r[2] for r in q):.3f}, inside twice / inside max {max(r[3] for r in q):.2f} ({len(q)})"
                   if q else "-")
        print(f"| {name} | {'; '.join(parts) or '-'} | "
              + (f"{len(p2s)}: alternative / with max {max(ratio):.2f}, gain max {max(gain):.2f}, warned {warn}"
                 if p2s else "-")
              + f" | {quarter} |")


def spconv_strides(vox: SparseVoxels, n: int):
    """``vox`` and ``n`` levels of SparseConv3d(kernel 3, stride 2, padding 1) on it."""
    import spconv.pytorch as spconv

    out, t = [vox], vox.to_spconv()
    conv = spconv.SparseConv3d(vox.features.shape[1], vox.features.shape[1], 3, 2, 1, bias=False)
    stride = 1
    for _ in range(n):
        t = conv(t)
        stride *= 2
        out.append(SparseVoxels.from_spconv(t, voxel_size=vox.voxel_size, point_range_min=vox.point_range_min, stride=(stride,) * 3))
    return out


def voxelize(points, voxel_size, point_range):
    sys.path.insert(0, str(ROOT / "examples"))
    from real_frame import voxelize_mean

    return voxelize_mean(points, voxel_size, point_range)


def real_frames(rec_name="real VoD frames") -> None:
    from mssf_examples.data.kitti_io import VOD_CLASSES, VOD_RADAR, KittiFormatDataset

    root = ROOT.parent / "shared" / "realdata" / "vod"
    if not root.exists():
        print(f"| {rec_name} | (no data at {root}) | | |")
        return
    ds = KittiFormatDataset(root, VOD_RADAR, class_names=VOD_CLASSES)
    g = torch.Generator().manual_seed(0)
    for grid in (VOD_GRID, COARSE):
        with Recorder() as rec, warnings.catch_warnings():
            warnings.simplefilter("error", MSSFGeometryWarning)
            for fid in ds.frame_ids:
                frame = ds.load(fid)
                for k in range(8):
                    u = torch.rand(3, generator=g, dtype=torch.float64).tolist()
                    aug = augmentation_matrix(flip_x=u[0] < 0.5, rotation=(u[1] - 0.5) * math.pi / 2,
                                              scale=0.95 + 0.1 * u[2]) if k else torch.eye(4, dtype=torch.float64)
                    pts = frame.points[:, :3].double()
                    pts = (torch.cat([pts, torch.ones(len(pts), 1, dtype=torch.float64)], 1) @ aug.T)[:, :3].float()
                    vox = voxelize(torch.cat([pts, frame.points[:, 3:]], 1), grid, RANGE)
                    proj = VoxelCentroidProjector()
                    for v in spconv_strides(vox, 2):
                        proj(v, pts, torch.zeros(len(pts), dtype=torch.long), frame.lidar2img.float()[None],
                             frame.image_size, torch.linalg.inv(aug).float()[None] if k else None)
        rec.report(f"{rec_name}, grid {grid}, 2 frames x 8 augmentations")


def cli_training(detector: str, scenes: int, steps: int) -> None:
    from mssf_examples.cli import commands as cli
    from mssf_examples.data.kitti_export import write_vod_tree
    from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset

    with tempfile.TemporaryDirectory() as tmp, Recorder() as rec, warnings.catch_warnings():
        warnings.simplefilter("error", MSSFGeometryWarning)
        cfg = SceneConfig(image_size=(128, 204))
        train = [SyntheticDataset("train", scenes, cfg, seed=5)[i] for i in range(scenes)]
        write_vod_tree(Path(tmp) / "vod", {"train": train})
        code = cli.main(["train", "--dataset", "vod", "--data-root", str(Path(tmp) / "vod"), "--preset", "tiny",
                         "--detector", detector, "--steps", str(steps), "--batch-size", "2", "--threads", "1",
                         "--no-progress", "--fusion-blocks", "2", "--out", str(Path(tmp) / "out")])
    assert code == 0, code
    rec.report(f"CLI training, {detector}, {scenes} generated scenes, {steps} steps of 2, augmentation on")


def demo_detectors() -> None:
    sys.path.insert(0, str(ROOT / "tests" / "examples"))
    from test_detectors import make_batch
    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.presets import TINY

    with Recorder() as rec, warnings.catch_warnings():
        warnings.simplefilter("error", MSSFGeometryWarning)
        for name in ("second", "centerpoint", "voxelnext", "pointpillars"):
            torch.manual_seed(0)
            model = build_detector(name, TINY, num_fusion_blocks=2, score_threshold=0.0, max_detections=20)
            for seed in range(3):
                model(make_batch(seed))
    rec.report("demo detectors (tests/examples/models/test_detectors.py's batch), TINY, 4 detectors x 3 batches")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=16)
    ap.add_argument("--steps", type=int, default=12)
    ap.add_argument("--detectors", nargs="+", default=["second", "pointpillars"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    print("| correct inputs | points in voxels (min per stride, samples) | points_to_sensor "
          "| image_size (raw points) |")
    print("|---|---|---|---|")
    real_frames()
    demo_detectors()
    for d in args.detectors:
        cli_training(d, args.scenes, args.steps)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
