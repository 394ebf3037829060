"""Benchmark: voxel centroids by sort/searchsorted join vs a dense B x D x H x W lookup table.

8 frames x 40,000 points on the VoD grid (voxel 0.05 x 0.05 x 0.125 m, x 0-51.2, y -25.6-25.6,
z -3-2, grid (D, H, W) = (41, 1024, 1024) at stride 1), at strides 1 and 8. Both formulations run in
this process on the same inputs; the script checks they agree and reports time and peak extra memory
as ratios dense / ours (higher is better for us).

Peak extra memory is the rise of the process's resident-set high-water mark (Linux ``VmHWM``, reset
through ``/proc/self/clear_refs`` before each run) over the resident size before the run. The script
re-executes itself with ``MALLOC_MMAP_THRESHOLD_=65536`` so that glibc serves every allocation above
64 KiB with mmap and returns it on free: freed heap is not silently reused, and the high-water mark
counts what each formulation really allocates.

Usage: ``python benchmarks/centroids.py [--frames 8] [--points 40000] [--repeats 3] [--json out.json]``
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from mssf_blocks.functional.geometry import voxel_centers, voxel_centroids

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import measure, reexec_with_mmap_threshold  # noqa: E402

VOXEL = (0.05, 0.05, 0.125)
LO = (0.0, -25.6, -3.0)
HI = (51.2, 25.6, 2.0)
BASE_SHAPE = (41, 1024, 1024)  # ceil(5 / 0.125) = 40 -> OpenPCDet pads z to 41


def make_frames(frames: int, points: int, seed: int = 0):
    """Radar-like frames: most points in object clusters, the rest scattered over the range."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(LO), torch.tensor(HI)
    pts, bat = [], []
    for b in range(frames):
        n_clu = points * 3 // 4
        centres = lo + (hi - lo) * torch.rand(200, 3, generator=g)
        which = torch.randint(0, 200, (n_clu,), generator=g)
        clu = centres[which] + torch.randn(n_clu, 3, generator=g) * torch.tensor([0.8, 0.8, 0.4])
        scat = lo + (hi - lo) * torch.rand(points - n_clu, 3, generator=g)
        p = torch.cat([clu, scat])
        p = torch.minimum(torch.maximum(p, lo), hi - 1e-4)
        pts.append(torch.cat([p, torch.randn(points, 4, generator=g)], 1))  # + RCS, v_r, v_rc, t
        bat.append(torch.full((points,), b, dtype=torch.long))
    return torch.cat(pts), torch.cat(bat)


def voxel_coords(points, batch, stride):
    idx = torch.floor((points[:, :3] - torch.tensor(LO)) / torch.tensor(VOXEL)).long()
    s = torch.tensor(stride[::-1])  # (sx, sy, sz) to match idx's x, y, z order
    zyx = (idx // s)[:, [2, 1, 0]]
    return torch.unique(torch.cat([batch[:, None], zyx], 1), dim=0).int()


def dense_table_centroids(points, batch, coords, shape, frames, stride):
    """The formulation we avoid: a dense (B, D, H, W) table from voxel coordinates to row index."""
    d, h, w = shape
    table = torch.full((frames, d, h, w), -1, dtype=torch.long)
    c = coords.long()
    table[c[:, 0], c[:, 1], c[:, 2], c[:, 3]] = torch.arange(c.shape[0])
    idx = torch.floor((points[:, :3] - torch.tensor(LO)) / torch.tensor(VOXEL)).long()
    s = torch.tensor(stride[::-1])
    zyx = (idx // s)[:, [2, 1, 0]]
    row = table[batch, zyx[:, 0], zyx[:, 1], zyx[:, 2]]
    hit = row >= 0
    n = c.shape[0]
    sums = torch.zeros(n, 3, dtype=points.dtype).index_add_(0, row[hit], points[hit, :3])
    cnt = torch.zeros(n, dtype=points.dtype).index_add_(0, row[hit], torch.ones(int(hit.sum()), dtype=points.dtype))
    centers = voxel_centers(coords, VOXEL, LO, stride, dtype=points.dtype)
    has = cnt > 0
    return torch.where(has[:, None], sums / cnt.clamp(min=1)[:, None], centers), has


def main(argv=None) -> int:
    reexec_with_mmap_threshold()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--points", type=int, default=40_000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)

    points, batch = make_frames(args.frames, args.points)
    rows = []
    for stride in [(1, 1, 1), (8, 8, 8)]:
        shape = tuple(-(-s // k) for s, k in zip(BASE_SHAPE, stride))
        coords = voxel_coords(points, batch, stride)
        ours = lambda: voxel_centroids(points, batch, coords, shape, args.frames, VOXEL, LO, stride, HI)  # noqa: E731
        dense = lambda: dense_table_centroids(points, batch, coords, shape, args.frames, stride)  # noqa: E731
        (c1, h1), (c2, h2) = ours(), dense()
        if not (torch.equal(h1, h2) and torch.allclose(c1, c2, atol=1e-5)):
            print(f"MISMATCH at stride {stride}", file=sys.stderr)
            return 1
        t_ours, m_ours = measure(ours, args.repeats)
        t_dense, m_dense = measure(dense, args.repeats)
        rows.append(dict(stride=stride, voxels=int(coords.shape[0]), grid=shape,
                         time_ours_s=t_ours, time_dense_s=t_dense, time_ratio=t_dense / t_ours,
                         peak_ours_mib=m_ours, peak_dense_mib=m_dense,
                         memory_ratio=m_dense / max(m_ours, 1e-3)))

    print(f"voxel_centroids: {args.frames} frames x {args.points} points, VoD grid {BASE_SHAPE}, "
          f"{args.threads} threads, torch {torch.__version__}")
    hdr = f"{'stride':>9} {'voxels':>8} {'ours ms':>9} {'dense ms':>9} {'time x':>7} {'ours MiB':>9} {'dense MiB':>10} {'memory x':>9}"
    print(hdr)
    for r in rows:
        print(f"{str(r['stride'][0]):>9} {r['voxels']:>8} {1e3 * r['time_ours_s']:>9.1f} {1e3 * r['time_dense_s']:>9.1f} "
              f"{r['time_ratio']:>7.2f} {r['peak_ours_mib']:>9.1f} {r['peak_dense_mib']:>10.1f} {r['memory_ratio']:>9.1f}")
    ok = all(r["memory_ratio"] >= 20 and r["time_ratio"] >= 1.0 for r in rows)
    print("target (peak memory < 1/20 of dense, time not worse):", "met" if ok else "NOT met")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
