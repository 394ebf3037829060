"""Benchmark: how far eager MSDFF sampling is from one core's limit (a measured gather / FMA roofline).

One process, one thread (``torch.set_num_threads(1)``), process CPU time (with one thread the work done,
robust to the other processes of a shared machine), median of ``--repeats`` calls after a warm-up.

1. The ceilings of one core, measured with the primitives the fast paths are built from:

   * FMA: float32 ``torch.mm`` GFLOP/s at a cache-friendly size (256 x 256 x 256, in L2) and a large one
     (2048 x 2048 x 2048);
   * row gather: rows of 256 float32 (1 KiB, the raw FPN channels) and of 32 (128 B, one head's width after
     ``value_proj``) read by ``index_select`` (into a reused buffer) and by ``embedding_bag(mode="sum")`` with
     ``per_sample_weights`` in bags of 16 rows (the 4 points x 4 bilinear corners of one head and level: what
     the sampling paths run, ``functional/deform/bag.py``, ``touched/``), in rows/s and GB/s, (i) at uniformly
     random indices from a table larger than the last-level cache (1 GiB; the host's L3 is 480 MiB, shared):
     the random-row ceiling; (ii) the same from a table the size of the largest level read (P2, 304 x 484
     pixels); (iii) from that table with ascending indices, each row read once at most: the best case
     without reuse (the paths take their queries in image order);
   * streaming copy bandwidth (``copy_`` of 256 MiB; read + write bytes), for reference.

2. Eager MSDFF at the paper's width (256 image channels, ``value_proj`` 256 -> 256, 8 heads, 4 levels,
   4 points; a View-of-Delft image 1216 x 1936, FPN strides 4, 8, 16, 32, channels-last levels; every voxel
   seen), N = 2,500 (32 voxel channels) and 8,000 (64), voxels "uniform" over the image and in the "radar
   band" (``benchmarks/msdff.py``'s layouts, parameters, features and reference, imported from it): the
   ``MSDFF`` module's forward (no grad, the default ``method="auto"``), its bilinear corner reads
   ``N x heads x levels x points x 4`` and corner reads / s, and the FLOPs of its projections. The FLOPs are
   a lower bound for any exact plan: the query-side GEMMs (``sampling_offsets``, ``attention_weights``),
   ``output_proj``, and ``value_proj`` on ``min(N, U)`` rows, ``U`` the pixels some bilinear corner reads
   summed over the levels (project those pixels, or sample the raw channels and project per query).

   The roofline bound of a case is the cheapest per-level mix of two plans, each mix bounded by
   ``max(gather time, FMA time)`` at the measured ceilings (perfect overlap): a level read "raw" (R) has every
   corner read a 256-channel row and needs ``value_proj`` on the N queries (once for all raw levels), a level
   read "touched" (T) has every corner read a 32-channel row and ``value_proj`` on its ``U_l`` touched pixels.
   The gather rate is the fastest ``embedding_bag`` rate measured at that width (on the host measured: the
   ascending one at 256 channels, the random P2-sized one at 32), so that the bound is a bound for reads
   without reuse (neighbouring points share corners: a path reusing rows in cache can beat
   it). The fractions: corner reads / s over the random-row ceiling and over the best rate, at 32 channels
   (the cheapest row any plan reads) and 256; the minimum FLOPs / s over the best GEMM rate.

3. The reference formulation (Deformable DETR's: ``value_proj`` over every pixel, ``F.grid_sample`` per
   level and head; ``benchmarks/msdff.py``'s ``ImagePath.reference``), timed in the same interleaved rounds as
   eager, and the ratio reference / eager (issue 45's goal: >= 12 at N = 2,500 and >= 8 at N = 8,000);
   reference / bound is the largest speed-up the roofline leaves to any exact plan.
   Each case checks eager agrees with the reference (max abs output difference).

Usage: ``python benchmarks/roofline.py [--quick] [--repeats 5] [--json out.json]``; ``--quick``: a
304 x 484 image, N = 300 / 1,000, 64 MiB tables, small GEMMs, one round (a few seconds;
tests/project/test_bench_roofline.py runs it).
"""

from __future__ import annotations

import argparse
import itertools
import os
import statistics
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import measure, print_table, write_json  # noqa: E402
from msdff import HEADS, IMAGE_CHANNELS, POINTS, ImagePath, corner_rows, make_features, voxel_uv  # noqa: E402

from mssf_blocks.geometry import CentroidProjection  # noqa: E402

LEVELS = 4  # strides 4, 8, 16, 32 (msdff.py's first four)
BAG = 16  # rows per bag: 4 points x 4 bilinear corners of one head and level
FULL = {"image": (1216, 1936), "cases": [(2500, 32), (8000, 64)], "table_bytes": 1 << 30, "gemm": (256, 2048),
        "rows": 1 << 20, "copy_bytes": 256 << 20, "repeats": 5}
QUICK = {"image": (304, 484), "cases": [(300, 32), (1000, 64)], "table_bytes": 64 << 20, "gemm": (128, 512),
         "rows": 1 << 16, "copy_bytes": 32 << 20, "repeats": 1}


def cpu_time(fn, repeats):
    """Median process CPU seconds of ``fn`` over ``repeats`` calls after one warm-up call."""
    return measure(fn, repeats, clock=time.process_time)[0]


def fma_ceiling(sizes, repeats):
    """Rows ``{"what", "GFLOP/s"}`` of square float32 GEMMs; a small one is repeated to last a few ms."""
    rows = []
    for n in sizes:
        a, b = torch.randn(n, n), torch.randn(n, n)
        out = torch.empty(n, n)
        reps = max(1, (512 // n) ** 3)
        t = cpu_time(lambda a=a, b=b, out=out, reps=reps: [torch.mm(a, b, out=out) for _ in range(reps)], repeats)
        rows.append({"what": f"torch.mm {n}^3 float32", "rate": 2 * n**3 * reps / t / 1e9, "unit": "GFLOP/s"})
    return rows


def gather_ceiling(buffer, width, table_rows, n_rows, repeats, label, ordered=False):
    """Random-row gather of ``n_rows`` rows of ``width`` float32 from the first ``table_rows`` rows of
    ``buffer``: ``index_select`` into a reused block and ``embedding_bag`` (sum, per-sample weights, bags of
    ``BAG``), in blocks of 65,536 rows (their outputs stay small). Returns two rows (rows/s, GB/s)."""
    table = buffer[: table_rows * width].view(table_rows, width)
    g = torch.Generator().manual_seed(width)
    if ordered:  # every row at most once, ascending: a gather's best case without reuse (the paths take their
        n_rows = min(n_rows, table_rows) // BAG * BAG  # queries in image order)
        idx = torch.randperm(table_rows, generator=g)[:n_rows].sort().values
    else:
        idx = torch.randint(0, table_rows, (n_rows,), generator=g)
    psw = torch.rand(n_rows, generator=g)
    block = min(n_rows, 1 << 16)
    out = torch.empty(block, width)

    def select():
        for s in range(0, n_rows, block):
            torch.index_select(table, 0, idx[s : s + block], out=out[: min(block, n_rows - s)])

    def bags():
        for s in range(0, n_rows, block):
            F.embedding_bag(idx[s : s + block].view(-1, BAG), table, per_sample_weights=psw[s : s + block].view(-1, BAG),
                            mode="sum")

    rows = []
    for name, fn in (("index_select", select), (f"embedding_bag sum, bags of {BAG}, weighted", bags)):
        t = cpu_time(fn, repeats)
        rows.append({"what": f"{name}: {width} ch rows from {label}", "width": width, "table": label,
                     "indices": "ascending" if ordered else "random",
                     "op": name.split(":")[0].split(",")[0], "rate": n_rows / t / 1e6, "unit": "M rows/s",
                     "GB/s": n_rows * width * 4 / t / 1e9})
    return rows


def copy_ceiling(nbytes, repeats):
    src = torch.ones(nbytes // 4)
    dst = torch.empty_like(src)
    t = cpu_time(lambda: dst.copy_(src), repeats)
    return {"what": f"copy_ of {nbytes >> 20} MiB (read + write)", "rate": 2 * nbytes / t / 1e9, "unit": "GB/s"}


def case_counts(path, query, uv, feats):
    """``(corner reads per level, touched pixels U_l per level, minimum FLOPs)`` of one case (the docstring)."""
    n, e = query.shape
    sizes = [f.shape[-2:] for f in feats]
    with torch.no_grad():
        loc, _ = path.locations_and_weights(query, uv, sizes)
    touched = [int(torch.unique(corner_rows(loc[:, :, lvl], h, w)).numel()) for lvl, (h, w) in enumerate(sizes)]
    corners = [n * HEADS * POINTS * 4] * len(sizes)
    d_v = path.value_proj.out_features
    query_side = 2 * n * (e + 2) * HEADS * LEVELS * POINTS * 3  # offsets (x, y) and attention weights
    flops = query_side + 2 * n * d_v * e + 2 * min(n, sum(touched)) * d_v * IMAGE_CHANNELS
    return corners, touched, flops


def roofline_bound(n, corners, touched, fixed_flops, ceil):
    """``(plan, gather s, FMA s)`` of the cheapest per-level mix of the two plans: a level read "raw" costs its
    corners at the 256-channel rate and puts ``value_proj`` on the N queries (once, whatever the number of raw
    levels), a level read "touched" its corners at the 32-channel rate and ``value_proj`` on its ``U_l`` pixels;
    each mix costs ``max(gather, FMA)`` (perfect overlap: a lower bound)."""
    per_row = 2 * IMAGE_CHANNELS * IMAGE_CHANNELS  # value_proj FLOPs per projected row
    best = None
    for mix in itertools.product(("raw", "touched"), repeat=len(corners)):
        gather = sum(c / ceil["bag256" if k == "raw" else "bag32"] for c, k in zip(corners, mix))
        rows = (n if "raw" in mix else 0) + sum(u for u, k in zip(touched, mix) if k == "touched")
        fma = (fixed_flops + per_row * rows) / ceil["fma"]
        if best is None or max(gather, fma) < max(best[1:]):
            best = ("/".join("R" if k == "raw" else "T" for k in mix), gather, fma)
    return best


def run_case(n, e, distribution, feats, repeats, ceil):
    torch.manual_seed(0)
    path = ImagePath(e, levels=LEVELS, value_dim=IMAGE_CHANNELS).eval()
    query = torch.randn(n, e)
    uv = voxel_uv(n, distribution)
    valid = torch.ones(n, 1, dtype=torch.bool)
    proj = CentroidProjection(uv[:, None], valid.float(), valid, torch.zeros(n, 3), valid[:, 0],
                              torch.zeros(n, dtype=torch.long))
    paths = {"eager": lambda: path.module(query, feats, proj), "reference": lambda: path.reference(query, uv, feats)}
    times = {k: [] for k in paths}
    with torch.no_grad():
        outs = {k: fn() for k, fn in paths.items()}  # (the warm-up)
        diff = float((outs["eager"] - outs["reference"]).abs().max())
        del outs
        for _ in range(repeats):  # interleaved rounds: a load change hits both alike
            for k, fn in paths.items():
                times[k].append(measure(fn, 1, warmup=0, clock=time.process_time)[0])
    t = {k: statistics.median(v) for k, v in times.items()}
    corners, touched, flops = case_counts(path, query, uv, feats)
    fixed = flops - 2 * min(n, sum(touched)) * IMAGE_CHANNELS * IMAGE_CHANNELS  # query side + output_proj
    bound_plan, g_s, f_s = roofline_bound(n, corners, touched, fixed, ceil)
    bound = max(g_s, f_s)
    corners, touched = sum(corners), sum(touched)
    return {"N": n, "C": e, "voxels": distribution, "max|out diff|": f"{diff:.1e}",
            "eager ms": 1e3 * t["eager"], "reference ms": 1e3 * t["reference"],
            "reference / eager": t["reference"] / t["eager"],
            "per-round ratios": f"{min(a / b for a, b in zip(times['reference'], times['eager'])):.2f}-"
                                f"{max(a / b for a, b in zip(times['reference'], times['eager'])):.2f}",
            "corner reads (M)": corners / 1e6, "touched pixels U": touched,
            "corner reads/s (M)": corners / t["eager"] / 1e6,
            "% of random gather > LLC (32 ch)": 100 * corners / t["eager"] / ceil["random32"],
            "% of random gather > LLC (256 ch)": 100 * corners / t["eager"] / ceil["random256"],
            "% of best gather (32 ch)": 100 * corners / t["eager"] / ceil["bag32"],
            "% of best gather (256 ch)": 100 * corners / t["eager"] / ceil["bag256"],
            "min GFLOP": flops / 1e9, "% of FMA ceiling": 100 * flops / t["eager"] / ceil["fma"],
            "bound plan": bound_plan, "bound gather ms": 1e3 * g_s, "bound FMA ms": 1e3 * f_s,
            "roofline bound ms": 1e3 * bound, "eager / bound": t["eager"] / bound,
            "reference / bound": t["reference"] / bound}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small image, sizes and tables, one round (seconds)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--json", default=None, help="write the results to this JSON file")
    args = ap.parse_args()
    cfg = QUICK if args.quick else FULL
    repeats = args.repeats or cfg["repeats"]
    torch.set_num_threads(1)
    load = os.getloadavg()
    feats = make_features(*cfg["image"])[:LEVELS]
    p2 = feats[0].shape[-2] * feats[0].shape[-1]
    print(f"image {cfg['image'][0]} x {cfg['image'][1]}, levels {[tuple(f.shape[-2:]) for f in feats]}, "
          f"{IMAGE_CHANNELS} ch, M={HEADS}, L={LEVELS}, P={POINTS}, threads={torch.get_num_threads()}, "
          f"repeats={repeats}, clock=process CPU, load average before={load[0]:.1f}")

    ceilings = fma_ceiling(cfg["gemm"], repeats)
    buffer = torch.ones(cfg["table_bytes"] // 4)  # touched pages (ones: a memset, cheaper than randn)
    big = f"{cfg['table_bytes'] >> 20} MiB"
    for width in (IMAGE_CHANNELS, IMAGE_CHANNELS // HEADS):
        p2_label = f"P2-sized ({p2 * width * 4 >> 20} MiB)"
        for rows, label, ordered in ((cfg["table_bytes"] // (4 * width), big, False), (p2, p2_label, False),
                                     (p2, p2_label + ", ascending, each row once", True)):
            ceilings += gather_ceiling(buffer, width, rows, cfg["rows"], repeats, label, ordered)
    del buffer
    ceilings.append(copy_ceiling(cfg["copy_bytes"], repeats))
    def bag_rate(width, table=None):  # rows/s: the fastest embedding_bag at this width (on this table)
        return 1e6 * max(r["rate"] for r in ceilings if r.get("op") == "embedding_bag sum" and r["width"] == width
                         and table in (None, r["table"]))

    ceil = {"fma": max(r["rate"] for r in ceilings if r["unit"] == "GFLOP/s") * 1e9,
            "bag256": bag_rate(IMAGE_CHANNELS), "bag32": bag_rate(IMAGE_CHANNELS // HEADS),
            "random256": bag_rate(IMAGE_CHANNELS, big), "random32": bag_rate(IMAGE_CHANNELS // HEADS, big)}
    print("\none-core ceilings")
    ceiling_table = print_table(ceilings, ["what", "rate", "unit", "GB/s"])

    rows = [run_case(n, e, dist, feats, repeats, ceil) for dist in ("uniform", "radar band") for n, e in cfg["cases"]]
    print(f"load average after={os.getloadavg()[0]:.1f}")
    key = ["N", "C", "voxels"]
    print("\neager MSDFF against the reference (process CPU time, interleaved rounds)")
    print_table(rows, key + ["eager ms", "reference ms", "reference / eager", "per-round ratios", "max|out diff|"])
    print("\neager MSDFF against the roofline")
    print_table(rows, key + ["corner reads (M)", "touched pixels U", "corner reads/s (M)",
                             "% of random gather > LLC (32 ch)", "% of random gather > LLC (256 ch)",
                             "% of best gather (32 ch)", "% of best gather (256 ch)", "min GFLOP", "% of FMA ceiling", "bound plan",
                             "bound gather ms", "bound FMA ms", "roofline bound ms", "eager ms", "eager / bound",
                             "reference / bound"])
    if args.json:
        write_json(args.json, {"image": cfg["image"], "levels": LEVELS, "threads": 1, "repeats": repeats,
                               "load_average": [load[0], os.getloadavg()[0]], "ceilings": ceilings,
                               "ceiling_table": ceiling_table, "rows": rows})


if __name__ == "__main__":
    main()
