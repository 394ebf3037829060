"""Benchmark: the MSDFF image path, project-every-pixel reference vs sample-then-project (ours).

VoD-like setting: one 1216 x 1936 camera image padded to a multiple of 32 (1216 x 1952), FPN levels
P2-P6 (strides 4, 8, 16, 32, 64; ``ceil(H / s) x ceil(W / s)``) with 256 channels, batch 1;
8 heads, 4 points, 5 levels; cases (N = 2,500 voxels, C = 32) and (N = 8,000, C = 64), every voxel
visible (Q = N queries). Two value widths (``--widths``): "paper" (MSDFF's default and the authors':
``value_proj`` 256 -> 256, 8 heads of 32 channels, ``output_proj`` 256 -> C) and "narrow" (``value_proj``
256 -> C, heads of C / 8, ``output_proj`` C -> C: ``MSDFF(value_dim=embed_dim)``). All paths compute the
same thing from the same inputs and parameters (an ``MSDFF``'s), and all take their sampling locations
and weights from ``MSDFF.sampling_locations_and_weights``, as the module does:

* reference (Deformable DETR's pure-PyTorch formulation): ``value_proj`` (Linear 256 -> D_v) over every
  pixel of every level, per-level ``F.grid_sample`` of the per-head values
  (``ms_deform_sample(method="reference")``, Mv = M, D = D_v / M), weighted sum, ``output_proj``;
* fast: ``ms_deform_sample(method="fast", Mv=1, return_mass=True)`` on the raw 256-channel maps, then
  the per-head value projection (einsum with ``value_proj.weight`` split per head) + ``bias * mass``,
  then ``output_proj``.

A third row, "fused", is ``ms_deform_sample_project(method="chunked")`` (sampling and the per-head
projection per (chunk of queries, level), recomputed in backward): the same result with memory
bounded by the chunk size. A fourth row, "touched", is ``ms_deform_sample_project(method="touched")``
(what ``MSDFF(value_projection="before_sampling")`` runs): per level, project only the pixels that
some bilinear corner reads (the whole level when the cost model says that is cheaper) with one GEMM,
then sample ``C / M`` channels per head.

Two spatial distributions of the voxels' projections: "uniform" (spread uniformly over the whole
image: the worst case, most pixels of P2 are near some sampling point at N >= 2,500) and "radar band"
(uniform over ``u`` in [0.06, 0.85], ``v`` in [0.49, 0.89] of the image: the 5 %-95 % quantiles of the
projections of the radar points of the two View-of-Delft frames under ``../shared/realdata/vod``
(00549, 01047), measured with ``mssf_examples.data.kitti_io``; real radar points concentrate there, below
the horizon; 32 % of the image area). The targets are judged on "uniform".

The script checks every path agrees with the reference (max abs output difference and max relative
gradient difference printed) and reports, as ratios reference / ours (higher is better for us):
forward time, forward+backward time, peak extra memory of forward and of forward+backward; plus
time(2x image area) / time(1x) (lower is better; the 2x image is 1728 x 2752). Backward is w.r.t.
the query-side parameters (``sampling_offsets``, ``attention_weights``), the queries (hence
locations and weights), ``value_proj`` and ``output_proj``; the image features are frozen, as in
the paper (the image branch is pre-trained and frozen). Features are allocated channels-last, the
layout PyTorch's CPU convolutions produce fastest, so that the fast path reads them through a free
``(pixels, 256)`` view; the reference reads them through a free permuted view as well. Voxels are
spread uniformly over the image (the worst case for memory locality).

A last table bounds what any exact method can reach with PyTorch's CPU primitives
(:func:`primitive_floor`): per level the cheaper of a GEMM over the touched pixels and an
``embedding_bag`` over the raw corner rows, index work free; ``fwd bound`` = reference / floor.

Time: median of ``--repeats`` interleaved rounds (one call of every path per round) after a warm-up; ``torch.set_num_threads(2)`` (``--threads``);
wall time, or with ``--cpu-time`` the process CPU time (with one thread: the work done, robust to the
other processes of a shared machine). Times are taken in this process, with glibc's default allocator
settings (what a user's process runs with). The ratios are ratios of the medians; a second table
gives, for each ratio, the lowest and highest of its per-round values (the reference and ours timed
back to back in that round), the spread a single figure hides on a shared machine. Peak extra memory
is measured in a second process (the script re-runs itself with ``--memory-pass``): the rise of the
resident-set high-water mark over a call (see ``benchmarks/_common.py``), which needs glibc to ``mmap``
every allocation above 64 KiB, so that every such allocation also pays its page faults on every call
(expensive in the VM we measure on).
That pass also records its own times; they are reported as "(mmap) ms" columns, not used for the
ratios. ``--no-memory`` skips the second pass.

Usage: ``python benchmarks/msdff.py [--quick] [--repeats 3] [--threads 2] [--chunk-size 1024]
[--kinds fast fused touched] [--distributions uniform "radar band"] [--widths paper narrow]
[--no-memory] [--json out.json]``
"""

from __future__ import annotations

import argparse
import functools
import math
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import measure, print_table, reexec_with_mmap_threshold, round_spread, write_json  # noqa: E402

_measure = measure

from mssf_blocks import MSDFF  # noqa: E402
from mssf_blocks.functional import ms_deform_sample, ms_deform_sample_project  # noqa: E402
from mssf_blocks.functional.plan_costs import _RAW_CHUNK_BYTES  # noqa: E402
from mssf_blocks.functional.deform.touched.order import _spatial_order  # noqa: E402

STRIDES = (4, 8, 16, 32, 64)
IMAGE_CHANNELS = 256
HEADS, POINTS = 8, 4


class ImagePath(nn.Module):
    """The parameters of MSDFF's image path (Deformable DETR names) and its two formulations.

    The parameters are an :class:`~mssf_blocks.MSDFF`'s, and both formulations take their sampling
    locations and weights from the module's own ``sampling_locations_and_weights`` (what MSDFF's forward
    runs; one GEMM for the locations, in the level-major memory the samplers read by rows), so that
    the paths differ only in how they sample and project the image.
    """

    def __init__(self, embed_dim: int, levels: int = len(STRIDES), value_dim: int = None) -> None:
        super().__init__()
        m, l, p = HEADS, levels, POINTS
        value_dim = embed_dim if value_dim is None else value_dim
        self.m, self.l, self.p, self.d = m, l, p, value_dim // m
        self.module = MSDFF(IMAGE_CHANNELS, embed_dim, value_dim=value_dim, num_heads=m, num_levels=l,
                            num_points=p, norm_layer=None)
        self.sampling_offsets = self.module.sampling_offsets
        self.attention_weights = self.module.attention_weights
        self.value_proj = self.module.value_proj
        self.output_proj = self.module.output_proj
        # Deformable DETR start (direction grid of 1..P pixels per head) plus small query-dependent
        # offsets and weights, so that points differ between queries as after training.
        g = torch.Generator().manual_seed(1)
        with torch.no_grad():
            th = torch.arange(m, dtype=torch.float64) * (2 * math.pi / m)
            grid = torch.stack([th.cos(), th.sin()], -1)
            grid = grid / grid.abs().max(-1, keepdim=True).values
            grid = grid.view(m, 1, 1, 2).repeat(1, l, p, 1) * torch.arange(1, p + 1).view(1, 1, p, 1)
            self.sampling_offsets.bias.copy_(grid.reshape(-1).float())
            self.sampling_offsets.weight.normal_(0, 0.5, generator=g)
            self.attention_weights.weight.normal_(0, 0.1, generator=g)

    def locations_and_weights(self, query, uv, sizes):
        """``(Q, M, L, P, 2)`` locations ``uv + offset / (W_l, H_l)`` and ``(Q, M, L, P)`` softmax weights."""
        return self.module.sampling_locations_and_weights(query, uv, sizes)

    def reference(self, query, uv, feats):
        loc, wt = self.locations_and_weights(query, uv, [f.shape[-2:] for f in feats])
        values = []
        for f in feats:  # every pixel of every level goes through value_proj
            h, w = f.shape[-2:]
            v = self.value_proj(f.permute(0, 2, 3, 1))  # (1, h, w, D_v)
            values.append(v.view(1, h, w, self.m, self.d).permute(0, 3, 4, 1, 2))  # (1, M, d, h, w)
        img_index = torch.zeros(query.shape[0], dtype=torch.long)
        out = ms_deform_sample(values, img_index, loc, wt, method="reference")  # (Q, M, d)
        return self.output_proj(out.reshape(query.shape[0], -1))

    def fast(self, query, uv, feats):
        loc, wt = self.locations_and_weights(query, uv, [f.shape[-2:] for f in feats])
        values = [f.view(1, 1, IMAGE_CHANNELS, *f.shape[-2:]) for f in feats]  # views, Mv = 1
        img_index = torch.zeros(query.shape[0], dtype=torch.long)
        sampled, mass = ms_deform_sample(values, img_index, loc, wt, method="fast", return_mass=True)
        w_heads = self.value_proj.weight.view(self.m, self.d, IMAGE_CHANNELS)
        b_heads = self.value_proj.bias.view(self.m, self.d)
        heads = torch.einsum("qmc,mdc->qmd", sampled, w_heads) + mass[..., None] * b_heads
        return self.output_proj(heads.reshape(query.shape[0], -1))

    def _sample_project(self, query, uv, feats, **method):
        """``ms_deform_sample_project`` on the raw maps (Mv = 1) with this path's per-head value_proj."""
        loc, wt = self.locations_and_weights(query, uv, [f.shape[-2:] for f in feats])
        values = [f.view(1, 1, IMAGE_CHANNELS, *f.shape[-2:]) for f in feats]
        img_index = torch.zeros(query.shape[0], dtype=torch.long)
        heads = ms_deform_sample_project(
            values, img_index, loc, wt,
            self.value_proj.weight.view(self.m, self.d, IMAGE_CHANNELS), self.value_proj.bias.view(self.m, self.d),
            **method,
        )
        return self.output_proj(heads.reshape(query.shape[0], -1))

    def touched(self, query, uv, feats):
        return self._sample_project(query, uv, feats, method="touched")

    def fused(self, query, uv, feats, chunk_size=1024):
        return self._sample_project(query, uv, feats, chunk_size=chunk_size)

def corner_rows(loc: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """``(Q * M, P * 4)`` pixel ids ``y * W + x`` of the 4 bilinear corners of ``loc (Q, M, P, 2)``
    (align_corners=False); corners outside the map read pixel 0 (a valid row: only speed matters)."""
    x = loc[..., 0] * w - 0.5
    y = loc[..., 1] * h - 0.5
    x0, y0 = x.floor().long(), y.floor().long()
    ids = []
    for dy in (0, 1):
        for dx in (0, 1):
            xx, yy = x0 + dx, y0 + dy
            inside = (xx >= 0) & (xx < w) & (yy >= 0) & (yy < h)
            ids.append(torch.where(inside, yy * w + xx, 0))
    return torch.stack(ids, -1).reshape(loc.shape[0] * loc.shape[1], -1)


def primitive_floor(path: "ImagePath", query, uv, feats, repeats: int):
    """Forward time below which no exact method built from PyTorch's CPU primitives can go.

    Per level, an exact method must either project the ``U_l`` pixels that some bilinear corner
    reads (a GEMM over ``U_l`` rows: timed on a contiguous stand-in, no gather counted) or read the
    raw channels of every corner (``embedding_bag`` over the level's channels-last rows at the real
    corner ids, queries in image order and bagged in blocks like the touched plans, no weights or
    per-head projection counted); the floor is the cheaper of the two per
    level, plus the locations/weights and ``output_proj`` that every formulation computes. The index
    work (corner weights, cell ids) and the rest of either route are free here, so the bound is
    generous. Returns ``(floor seconds, [(touched fraction, gemm s, bag s) per level])``.
    """
    with torch.no_grad():
        sizes = [f.shape[-2:] for f in feats]
        shared = measure(lambda: path.locations_and_weights(query, uv, sizes), repeats)[0]
        heads = torch.zeros(query.shape[0], path.output_proj.in_features)
        shared += measure(lambda: path.output_proj(heads), repeats)[0]
        loc, _ = path.locations_and_weights(query, uv, sizes)
        # the queries in image order, as the touched plans take them (rows of neighbours in cache)
        loc = loc[_spatial_order(torch.zeros(loc.shape[0], dtype=torch.long), loc, sizes)]
        levels = []
        for lvl, f in enumerate(feats):
            h, w = f.shape[-2:]
            table = f.permute(0, 2, 3, 1).reshape(h * w, IMAGE_CHANNELS)  # free view of channels-last maps
            levels.append(level_floor(loc[:, :, lvl], h, w, table, path.value_proj.weight, repeats, measure))
    return shared + sum(min(g, b) for _, g, b in levels), levels


def level_floor(loc, h: int, w: int, table, weight, repeats: int, timer):
    """``(touched fraction, GEMM s, bag s)`` of one level: the GEMM that projects the pixels some
    bilinear corner of ``loc (Q, M, P, 2)`` (queries in image order) reads, ``weight (E, C)`` on a
    contiguous stand-in of those rows, and the ``embedding_bag`` of every corner's row of
    ``table (h * w, C)``, in blocks of queries as the touched plans bag them (one ``(M * Q, C)``
    output would pay its page faults on every call). ``timer`` is :func:`_common.measure` or a
    variant of it."""
    rows = corner_rows(loc, h, w)
    touched = torch.zeros(h * w, dtype=torch.bool)
    touched[rows.reshape(-1)] = True
    u = int(touched.sum())
    stand_in = torch.randn(u, table.shape[1])
    t_gemm = timer(lambda: F.linear(stand_in, weight), repeats)[0]
    psw = torch.rand(rows.shape)
    block = max(1, _RAW_CHUNK_BYTES // (loc.shape[1] * table.shape[1] * 4)) * loc.shape[1]  # bags per block
    t_bag = timer(lambda: [F.embedding_bag(rows[s : s + block], table, per_sample_weights=psw[s : s + block],
                                           mode="sum") for s in range(0, rows.shape[0], block)], repeats)[0]
    return u / (h * w), t_gemm, t_bag


def make_features(height: int, width: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    feats = []
    for s in STRIDES:
        f = torch.randn(1, IMAGE_CHANNELS, -(-height // s), -(-width // s), generator=g)
        feats.append(f.contiguous(memory_format=torch.channels_last))  # frozen: no requires_grad
    return feats


# 5 %-95 % quantiles of (u / W, v / H) of the in-image radar points of VoD frames 00549 and 01047.
RADAR_BAND = ((0.06, 0.85), (0.49, 0.89))


def voxel_uv(n: int, distribution: str) -> torch.Tensor:
    uv = torch.rand(n, 2)
    if distribution == "radar band":
        (u0, u1), (v0, v1) = RADAR_BAND
        uv = uv * torch.tensor([u1 - u0, v1 - v0]) + torch.tensor([u0, v0])
    return uv


def run_case(n: int, c: int, distribution: str, feats, feats2x, repeats: int, chunk_size: int, kinds_wanted,
             seed: int = 0, width: str = "narrow", memory_pass: bool = False):
    """One case's row: agreement, times, ratios and the floor; with ``memory_pass`` only the peak
    memory (and the times taken under the memory measurement's allocator)."""
    torch.manual_seed(seed)
    path = ImagePath(c, value_dim=IMAGE_CHANNELS if width == "paper" else c)
    query = torch.randn(n, c, requires_grad=True)
    uv = voxel_uv(n, distribution)
    grad_out = torch.randn(n, c)
    params = [query] + [p for p in path.parameters()]
    all_kinds = {
        "reference": path.reference,
        "fast": path.fast,
        "fused": lambda q, u, f: path.fused(q, u, f, chunk_size=chunk_size),
        "touched": path.touched,
    }
    kinds = {k: v for k, v in all_kinds.items() if k == "reference" or k in kinds_wanted}
    ours = [k for k in kinds if k != "reference"]

    def fwd(kind, fs):
        def f():
            with torch.no_grad():
                return kinds[kind](query, uv, fs)
        return f

    def fwd_bwd(kind, fs):
        def f():
            return torch.autograd.grad(kinds[kind](query, uv, fs), params, grad_out)
        return f

    row = {"width": width, "N": n, "C": c, "voxels": distribution}
    if memory_pass:
        for kind in kinds:
            for label, fn in (("fwd", fwd(kind, feats)), ("fwd+bwd", fwd_bwd(kind, feats))):
                t, mib = measure(fn, repeats)
                row[f"{kind} {label} MiB"], row[f"{kind} {label} (mmap) ms"] = mib, 1e3 * t
        for kind in ours:
            for label in ("fwd", "fwd+bwd"):
                row[f"{kind} {label} mem ratio"] = row[f"reference {label} MiB"] / max(row[f"{kind} {label} MiB"], 1e-3)
        return row
    # Agreement of outputs and of every gradient with the reference.
    out_r = path.reference(query, uv, feats)
    g_r = torch.autograd.grad(out_r, params, grad_out)
    for kind in ours:
        out_k = kinds[kind](query, uv, feats)
        g_k = torch.autograd.grad(out_k, params, grad_out)
        row[f"{kind} max|out diff|"] = (out_r - out_k).abs().max().item()
        row[f"{kind} max rel grad diff"] = max(
            ((a - b).abs().max() / b.abs().max().clamp(min=1e-12)).item() for a, b in zip(g_k, g_r)
        )
        del out_k, g_k
    del out_r, g_r

    # Interleaved rounds (one call of every kind per round, after a warm-up call each), so that a load
    # change on the shared machine hits the reference and ours alike; the median per kind.
    # The 1x and 2x image forwards share their rounds (their ratio is a target too).
    rounds = {}  # (kind, mode) -> the seconds of every round
    for group in ((("fwd", fwd, feats), ("fwd2x", fwd, feats2x)), (("fwdbwd", fwd_bwd, feats),)):
        fns = {(kind, mode): make(kind, fs) for mode, make, fs in group for kind in kinds}
        for fn in fns.values():
            fn()
        rounds.update({key: [] for key in fns})
        for _ in range(repeats):
            for key, fn in fns.items():
                rounds[key].append(measure(fn, 1, warmup=0)[0])
    res = {key: statistics.median(t) for key, t in rounds.items()}  # seconds
    for kind in kinds:
        row[f"{kind} fwd ms"] = 1e3 * res[kind, "fwd"]
        row[f"{kind} fwd+bwd ms"] = 1e3 * res[kind, "fwdbwd"]
        row[f"{kind} 2x-area fwd"] = res[kind, "fwd2x"] / res[kind, "fwd"]
    floor, levels = primitive_floor(path, query, uv, feats, repeats)
    row["floor fwd ms"] = 1e3 * floor
    row["fwd bound"] = res["reference", "fwd"] / floor
    row["floor per level (touched, gemm ms, bag ms)"] = "; ".join(
        f"P{i + 2} {t:.0%} {1e3 * g:.1f} {1e3 * b:.1f}" for i, (t, g, b) in enumerate(levels))
    for kind in ours:
        row[f"{kind} fwd speed-up"] = res["reference", "fwd"] / res[kind, "fwd"]
        row[f"{kind} fwd+bwd speed-up"] = res["reference", "fwdbwd"] / res[kind, "fwdbwd"]
        row[f"{kind} fwd speed-up rounds"] = round_spread(rounds["reference", "fwd"], rounds[kind, "fwd"])
        row[f"{kind} fwd+bwd speed-up rounds"] = round_spread(rounds["reference", "fwdbwd"], rounds[kind, "fwdbwd"])
    for kind in kinds:
        row[f"{kind} 2x-area fwd rounds"] = round_spread(rounds[kind, "fwd2x"], rounds[kind, "fwd"])
    return row


KINDS = ("reference", "fast", "fused", "touched")
RATIO_KEYS = ("fwd speed-up", "fwd+bwd speed-up", "fwd mem ratio", "fwd+bwd mem ratio", "2x-area fwd")


def memory_pass(argv):
    """Re-run this script with ``--memory-pass`` (its own process, glibc's mmap threshold at 64 KiB) and
    return its rows."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "memory.json")
        argv = [a for a in argv if a != "--no-memory"]
        subprocess.run([sys.executable, os.path.abspath(__file__), *argv, "--memory-pass", out], check=True,
                       stdout=subprocess.DEVNULL)
        with open(out) as f:
            return json.load(f)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="608 x 976 image, N = 1,000 / 3,000, 3 repeats")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--chunk-size", type=int, default=1024, help="queries per chunk of the fused path")
    ap.add_argument("--json", default=None, help="write the results to this JSON file")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--kinds", nargs="+", default=list(KINDS[1:]), choices=KINDS[1:],
                    help="paths compared with the reference")
    ap.add_argument("--distributions", nargs="+", default=["uniform", "radar band"],
                    choices=["uniform", "radar band"], help="where the voxels project (see the docstring)")
    ap.add_argument("--cases", nargs="+", default=None, metavar="N:C",
                    help="voxels N and voxel channels C per case (default 500:32 2500:32 8000:64)")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time with the process CPU time instead of the wall time (use with --threads 1)")
    ap.add_argument("--widths", nargs="+", default=["paper", "narrow"], choices=["paper", "narrow"],
                    help="value widths: paper (value_proj 256 -> 256, output_proj 256 -> C) and/or narrow "
                         "(256 -> C, C -> C)")
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory pass (a second process)")
    ap.add_argument("--memory-pass", default=None, metavar="OUT.json", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.memory_pass:
        reexec_with_mmap_threshold()
    torch.set_num_threads(args.threads)
    if args.cpu_time:  # every measure() of this run reads the process CPU time
        global measure
        measure = functools.partial(_measure, clock=time.process_time)
    if args.quick:
        size, size2x, sizes, repeats = (608, 976), (864, 1376), [(1000, 32), (3000, 64)], 3
    else:
        size, size2x, sizes, repeats = (1216, 1952), (1728, 2752), [(500, 32), (2500, 32), (8000, 64)], 3
    if args.cases:
        try:
            sizes = [tuple(int(x) for x in case.split(":")) for case in args.cases]
        except ValueError:
            ap.error(f"--cases: expected N:C pairs, got {args.cases}")
    cases = [(n, c, dist, width) for width in args.widths for dist in args.distributions for n, c in sizes]
    repeats = args.repeats or repeats
    feats, feats2x = make_features(*size), make_features(*size2x, seed=1)
    load = os.getloadavg()
    print(f"image {size[0]} x {size[1]} (2x area: {size2x[0]} x {size2x[1]}), levels "
          f"{[tuple(f.shape[-2:]) for f in feats]}, {IMAGE_CHANNELS} ch, M={HEADS}, P={POINTS}, "
          f"threads={torch.get_num_threads()}, repeats={repeats}, fused chunk={args.chunk_size}, "
          f"clock={'process CPU' if args.cpu_time else 'wall'}, load average before={load[0]:.1f}, MALLOC_MMAP_THRESHOLD_={os.environ.get('MALLOC_MMAP_THRESHOLD_')}")
    if args.memory_pass:
        write_json(args.memory_pass, [run_case(n, c, dist, feats, feats2x, min(repeats, 2), args.chunk_size,
                                               args.kinds, width=width, memory_pass=True)
                                      for n, c, dist, width in cases])
        return
    rows = [run_case(n, c, dist, feats, feats2x, repeats, args.chunk_size, args.kinds, width=width)
            for n, c, dist, width in cases]
    if not args.no_memory:
        for row, mem in zip(rows, memory_pass(sys.argv[1:])):
            row.update(mem)
    print(f"load average after={os.getloadavg()[0]:.1f}")
    kinds = [k for k in KINDS if k == "reference" or k in args.kinds]
    ours = kinds[1:]
    key = ["width", "N", "C", "voxels"]
    agreement = key + [f"{k} {w}" for k in ours for w in ("max|out diff|", "max rel grad diff")]
    times = key + [f"{k} {w}" for w in ("fwd ms", "fwd+bwd ms") for k in kinds]
    memory = key + [f"{k} {w}" for w in ("fwd MiB", "fwd+bwd MiB", "fwd (mmap) ms", "fwd+bwd (mmap) ms")
                    for k in kinds]
    ratios = key + [f"{k} {w}" for k in ours for w in RATIO_KEYS] + ["reference 2x-area fwd"]
    spread = key + [f"{k} {w} rounds" for k in ours for w in RATIO_KEYS if "mem" not in w] + [
        "reference 2x-area fwd rounds"]
    floor = key + ["reference fwd ms", "floor fwd ms", "fwd bound", "floor per level (touched, gemm ms, bag ms)"]
    tables = {}
    for title, cols in (("agreement with the reference", agreement), ("median time (ms)", times),
                        ("peak extra memory (MiB; and the times under the memory pass's allocator)", memory), ("ratios", ratios),
                        ("per-round ratios, lowest-highest (the spread behind the medians above: each round's "
                         "calls ran back to back)", spread),
                        ("forward floor of PyTorch primitives (fwd bound = reference / floor: the largest "
                         "forward speed-up any exact method built from them can reach)", floor)):
        print(f"\n{title}")
        tables[title] = print_table(rows, cols)
    if args.json:
        write_json(args.json, {"image": size, "image_2x": size2x, "threads": torch.get_num_threads(),
                               "load_average": load, "rows": rows})


if __name__ == "__main__":
    main()
