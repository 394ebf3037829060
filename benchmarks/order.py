"""Benchmark: the order in which the ``"touched"`` plans take the queries (``_SORT_CELL`` in
``src/mssf_blocks/functional/plan_costs.py``).

``benchmarks/msdff.py``'s setting (one 1216 x 1952 image, P2-P6 with 256 channels in channels-last
memory, 8 heads x 4 points, MSDFF at the paper's width, its ``touched`` path), with the queries put
in each of these orders before they are sampled (``_spatial_order`` swapped in the same process):

* ``callers``: no sort;
* ``bands``: by 64 bands of rows, then along ``u`` (the order until 2026-12-02);
* ``z``: Z (Morton) order of cells of about 2 pixels of P2;
* ``hilbert-1``, ``hilbert-2``, ``hilbert-4``: along a Hilbert curve of cells of 1, 2 or 4 pixels of
  P2 (``hilbert-2`` is the library's).

Every order gives the same output (checked each run, bit for bit in forward). Times are medians of
interleaved rounds (one call of every order per round, cases one after another), process CPU time,
one thread; ratios are against ``bands`` (lower is faster). The forward and, with ``--backward``,
forward + backward (w.r.t. the queries and MSDFF's parameters; the image is frozen, as in the paper).

Usage: ``python benchmarks/order.py [--rounds 7] [--backward] [--cases 2500:32 8000:64]
[--distributions uniform "radar band"]`` (about 1 minute forward only, 3 with ``--backward`` and 9 rounds).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import print_table  # noqa: E402
from msdff import ImagePath, make_features, voxel_uv  # noqa: E402

from mssf_blocks.functional.deform import touched as touched_mod  # noqa: E402
from mssf_blocks.functional.deform.touched import order as order_mod  # noqa: E402

LIBRARY_ORDER = order_mod._spatial_order


def bands(image_index, locations, sizes):
    ref = locations[:, 0, 0, 0].detach().clamp(0.0, 1.0)
    band = (ref[:, 1] * 63).round().long()
    return torch.argsort((image_index * 64 + band) * 4096 + (ref[:, 0] * 4095).round().long())


def z_order(image_index, locations, sizes):
    x, y, bits = order_mod._sort_cells(locations, sizes, 2.0)  # (the library's cells)
    key = torch.zeros_like(x)
    for b in range(bits):  # interleave the bits of x and y
        key |= ((x >> b) & 1) << (2 * b) | ((y >> b) & 1) << (2 * b + 1)
    return torch.argsort(image_index * (1 << (2 * bits)) + key)


def hilbert(cell):
    return lambda image_index, locations, sizes: LIBRARY_ORDER(image_index, locations, sizes, cell=cell)


ORDERS = {
    "callers": lambda image_index, locations, sizes: torch.arange(locations.shape[0]),
    "bands": bands,
    "z": z_order,
    "hilbert-1": hilbert(1.0),
    "hilbert-2": hilbert(2.0),
    "hilbert-4": hilbert(4.0),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--backward", action="store_true", help="also time forward + backward")
    ap.add_argument("--cases", nargs="+", default=["2500:32", "8000:64"], metavar="N:C")
    ap.add_argument("--distributions", nargs="+", default=["uniform", "radar band"],
                    choices=["uniform", "radar band"])
    args = ap.parse_args()
    torch.set_num_threads(1)
    feats = make_features(1216, 1952)
    cases = []
    for spec in args.cases:
        n, c = (int(x) for x in spec.split(":"))
        for dist in args.distributions:
            torch.manual_seed(0)
            path = ImagePath(c, value_dim=256)
            query = torch.randn(n, c, requires_grad=True)
            cases.append((f"{n}, {dist}", path, query, voxel_uv(n, dist)))
    modes = ["fwd", "fwd+bwd"] if args.backward else ["fwd"]
    print(f"threads=1, clock=process CPU, rounds={args.rounds}, load average before={os.getloadavg()[0]:.1f}")
    times = {(case[0], mode, name): [] for case in cases for mode in modes for name in ORDERS}
    first = {}
    try:
        for name, order in ORDERS.items():  # warm-up and agreement
            order_mod._spatial_order = order
            for label, path, query, uv in cases:
                with torch.no_grad():
                    out = path.touched(query, uv, feats)
                if name == "callers":
                    first[label] = out
                elif not torch.equal(out, first[label]):
                    raise SystemExit(f"order {name} changed the forward output ({label})")
        for _ in range(args.rounds):
            for label, path, query, uv in cases:
                for mode in modes:
                    for name, order in ORDERS.items():
                        order_mod._spatial_order = order
                        t0 = time.process_time()
                        with torch.set_grad_enabled(mode == "fwd+bwd"):
                            out = path.touched(query, uv, feats)
                            if mode == "fwd+bwd":
                                out.square().sum().backward()
                        times[(label, mode, name)].append(time.process_time() - t0)
    finally:
        order_mod._spatial_order = LIBRARY_ORDER
    rows = []
    for label, *_ in cases:
        for mode in modes:
            base = statistics.median(times[(label, mode, "bands")])
            row = {"case": label, "pass": mode, "bands ms": 1e3 * base}
            row.update({f"{name} / bands": statistics.median(times[(label, mode, name)]) / base
                        for name in ORDERS if name != "bands"})
            rows.append(row)
    print(f"load average after={os.getloadavg()[0]:.1f}")
    print_table(rows, list(rows[0]))


if __name__ == "__main__":
    main()
