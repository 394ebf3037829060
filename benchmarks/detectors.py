"""Benchmark: per-frame CPU forward time of the four example detectors, radar-only vs. fusion.

A VoD-sized frame: 2,500 radar points from 5 scans (time index t in 0..4) inside the camera's field of
view on the VoD preset grid (voxels 0.05 x 0.05 x 0.125 m over x 0-51.2, y -25.6-25.6, z -3-2; pillars
0.16 m), one 1216 x 1936 camera. Image features are precomputed (the paper freezes the image branch):
four FPN levels of 256 channels at strides 4-32, random values, in channels-last memory (what the
examples' ``ImageBranch`` returns by default; ``--nchw`` for NCHW). Every detector runs in eval mode
(``torch.no_grad``, batch of one frame, decoding included) with ``n = 0`` (radar only) and ``n = 2``
fusion blocks (MSDFF, the paper's default, and SFF), in this process on the same frame. A last
column bounds what any exact MSDFF could reach: ``cpu ratio msdff floor`` = (radar-only time + the
floor of the two blocks' image sampling, :func:`msdff_floor`) / radar-only time, every other cost of
the fusion blocks left out. The configurations
of one detector are timed in interleaved rounds (one call of each per round, after a warm-up call),
so a load change on the shared machine hits all of them alike. Both the wall time and the process CPU
time (``time.process_time``) of every call are recorded; with one intra-op thread (the default) the CPU
time is the work done and much less sensitive to other processes on a shared machine than the wall
time, so the fusion overhead ratio ``t(n=2) / t(n=0)`` (target: at most 1.30) is given on medians of
both; ``cpu ratio msdff rounds`` gives the lowest and highest of the rounds' own CPU-time ratios (the
spread a single median hides on a shared machine).

MSDFF runs at the paper's width (``value_proj`` 256 -> 256, ``output_proj`` 256 -> C, the library's
default); ``--msdff-width narrow`` measures the narrow layout (``value_dim`` = voxel channels) instead.

Usage: ``python benchmarks/detectors.py [--points 2500] [--repeats 7] [--threads 1] [--nchw]
[--detectors second centerpoint voxelnext pointpillars] [--msdff-width paper] [--no-floor] [--json out.json]``
"""

from __future__ import annotations

import argparse
import functools
import math
from dataclasses import replace
import os
import statistics
import sys
import time

import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _common import measure, print_table, round_spread, write_json  # noqa: E402
from mssf_examples.data.batch import RadarCameraBatch  # noqa: E402
from mssf_examples.models.detectors import build_detector  # noqa: E402
from mssf_examples.models.presets import VOD  # noqa: E402

IMAGE_H, IMAGE_W = VOD.image_size
FOCAL = 1260.0  # roughly VoD's camera


def vod_frame(num_points: int, seed: int = 0, channels_last: bool = False) -> RadarCameraBatch:
    """One frame: radar points in the camera's view, a pinhole camera at the origin looking along +x."""
    g = torch.Generator().manual_seed(seed)
    x = 1.0 + torch.rand(num_points, generator=g) ** 0.7 * 49.0  # denser near the sensor
    half_fov = math.atan((IMAGE_W / 2) / FOCAL)
    y = (torch.rand(num_points, generator=g) * 2 - 1) * x * math.tan(half_fov) * 0.95
    y = y.clamp(-25.5, 25.5)
    z = torch.rand(num_points, generator=g) * 4.0 - 2.5
    feats = torch.stack([
        torch.randn(num_points, generator=g) * 5,  # RCS
        torch.randn(num_points, generator=g),  # v_r
        torch.randn(num_points, generator=g),  # v_rc
        torch.randint(0, 5, (num_points,), generator=g).float(),  # scan index t
    ], 1)
    points = torch.cat([torch.stack([x, y, z], 1), feats], 1)
    l2i = torch.zeros(1, 1, 3, 4)
    l2i[0, 0, 0, 1], l2i[0, 0, 1, 2], l2i[0, 0, 2, 0] = -FOCAL, -FOCAL, 1.0
    l2i[0, 0, 0, 0], l2i[0, 0, 1, 0] = IMAGE_W / 2, IMAGE_H / 2
    levels = [torch.randn(1, 1, VOD.fpn_channels, math.ceil(IMAGE_H / s), math.ceil(IMAGE_W / s), generator=g)
              for s in (4, 8, 16, 32)]
    if channels_last:  # same values, (B, V, H, W, C) memory order (what a channels-last image branch returns)
        levels = [f.permute(0, 1, 3, 4, 2).contiguous().permute(0, 1, 4, 2, 3) for f in levels]
    return RadarCameraBatch(points=[points], lidar2img=l2i, image_features=levels, image_size=(IMAGE_H, IMAGE_W))


def msdff_floor(model, frame, repeats: int = 3):
    """Seconds below which no exact method built from PyTorch's CPU primitives can take the image
    sampling of ``model``'s MSDFF blocks on ``frame`` (``benchmarks/msdff.py``'s ``primitive_floor``
    per captured call): per block and level the cheaper of a GEMM that projects the pixels some corner
    reads (``U_l x C -> value_dim``, contiguous stand-in rows: no gather counted) and an
    ``embedding_bag`` of the raw channels of every corner (channels-last stand-in of the level, queries
    in image order, blocks of 4 MiB; no weights, projection or index work counted). Returns
    ``(seconds, [(voxels, seconds) per block])``."""
    from msdff import level_floor  # noqa: E402  (this folder)
    from mssf_blocks import MSDFF
    from mssf_blocks.functional.deform.touched.order import _spatial_order

    calls = []
    hooks = [mod.register_forward_pre_hook(lambda mod, args: calls.append((mod, args)))
             for mod in model.modules() if isinstance(mod, MSDFF)]
    try:
        with torch.no_grad():
            model(frame)
    finally:
        for h in hooks:
            h.remove()
    timer = functools.partial(measure, clock=time.process_time)
    blocks = []
    with torch.no_grad():
        for mod, (query, feats, proj) in calls:
            sizes = [tuple(f.shape[-2:]) for f in feats]
            seen = proj.valid[:, 0]  # (one camera: the voxels it sees are the queries)
            loc, _ = mod.sampling_locations_and_weights(query[seen], proj.uv[seen, 0], sizes)
            loc = loc[_spatial_order(proj.batch_index[seen], loc, sizes)]
            total = 0.0
            for lvl, (h, w) in enumerate(sizes):
                table = torch.randn(h * w, mod.value_channels)  # a channels-last stand-in of the level
                _, t_gemm, t_bag = level_floor(loc[:, :, lvl], h, w, table, mod.value_proj.weight, repeats, timer)
                total += min(t_gemm, t_bag)
            blocks.append((loc.shape[0], total))
    return sum(t for _, t in blocks), blocks


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2500)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--detectors", nargs="+", default=["second", "centerpoint", "voxelnext", "pointpillars"])
    ap.add_argument("--nchw", action="store_true",
                    help="image features in NCHW memory order (ImageBranch(channels_last=False)); default: "
                         "channels-last, what ImageBranch returns by default")
    ap.add_argument("--msdff-width", choices=["paper", "narrow"], default="paper",
                    help="MSDFF value width: paper (value_dim = 256 FPN channels) or narrow (= voxel channels)")
    ap.add_argument("--no-floor", action="store_true", help="skip the floor of the MSDFF blocks' image sampling")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    preset = replace(VOD, msdff_value_dim=None if args.msdff_width == "paper" else "voxel_channels")
    torch.set_num_threads(args.threads)
    frame = vod_frame(args.points, channels_last=not args.nchw)
    configs = [("n=0", 0, "msdff"), ("n=2 msdff", 2, "msdff"), ("n=2 sff", 2, "sff")]
    rows = []
    for name in args.detectors:
        models = {}
        for label, n, fusion in configs:
            torch.manual_seed(0)
            models[label] = build_detector(name, preset, num_fusion_blocks=n, fusion=fusion,
                                           image_features="precomputed").eval()
        wall = {label: [] for label in models}
        cpu = {label: [] for label in models}
        with torch.no_grad():
            for label, model in models.items():
                model(frame)  # warm-up (spconv index tuning, allocator)
            for _ in range(args.repeats):
                for label, model in models.items():
                    c0, t0 = time.process_time(), time.perf_counter()
                    model(frame)
                    wall[label].append(time.perf_counter() - t0)
                    cpu[label].append(time.process_time() - c0)
            _, out, _, _ = models["n=2 msdff"].extract(frame)
        w = {label: statistics.median(t) for label, t in wall.items()}
        c = {label: statistics.median(t) for label, t in cpu.items()}
        row = {"detector": name}
        row.update({f"{label} cpu (s)": c[label] for label in models})
        row["cpu ratio msdff"] = c["n=2 msdff"] / c["n=0"]
        row["cpu ratio sff"] = c["n=2 sff"] / c["n=0"]
        row["wall ratio msdff"] = w["n=2 msdff"] / w["n=0"]
        row["wall ratio sff"] = w["n=2 sff"] / w["n=0"]
        row["cpu ratio msdff rounds"] = round_spread(cpu["n=2 msdff"], cpu["n=0"])
        row["voxels in fusion blocks"] = "/".join(str(s.num_voxels) for s in out.stages[:2])
        if not args.no_floor:
            floor, _ = msdff_floor(models["n=2 msdff"], frame)
            row["msdff sampling floor (s)"] = floor
            # the overhead no exact MSDFF sampling can go below, every other cost of fusion left out
            row["cpu ratio msdff floor"] = (c["n=0"] + floor) / c["n=0"]
        rows.append(row)
        print(", ".join(f"{k}: {v:.3f}" if isinstance(v, float) else f"{k}: {v}" for k, v in row.items()), flush=True)
    print(f"\n{args.points} points, threads={args.threads}, {args.repeats} interleaved rounds (median), "
          f"MSDFF value projection {VOD.msdff_value_projection!r}, MSDFF width {args.msdff_width}, "
          f"image features {'NCHW' if args.nchw else 'channels-last'}, "
          f"torch {torch.__version__}\n")
    print_table(rows, list(rows[0].keys()))
    if args.json:
        write_json(args.json, {"points": args.points, "threads": args.threads, "rows": rows})


if __name__ == "__main__":
    main()
