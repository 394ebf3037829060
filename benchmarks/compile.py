"""``torch.compile`` of the fusion blocks: compile time, recompiles across voxel counts, speed vs eager.

For SFF, MSDFF and a FusionBlock (MSDFF + QueryInit, centroids and projection included) on one frame of
a 384 x 640 image with four 64-channel FPN levels (strides 8-64), and for README.md's drop-in example
(``README``: ``FusionBlock(MSDFF(256, 32), grid, query_init=True)`` at its widths and geometry, two samples of
a 320 x 512 image, 256-channel levels at strides 4-32: ``_readme_block.py``), forward in eval mode under
``torch.no_grad`` (deployment) and forward + backward in training mode:

* ``compile_s``: the first call of ``torch.compile(module, fullgraph=True, dynamic=True)`` (inductor
  unless ``--backend``), i.e. tracing + code generation + the C++ build;
* ``new_sizes_s``: the median call at four further voxel counts (no recompilation: close to steady);
* ``first_graphs``: graphs the first call compiled (2: dynamo restarted its analysis once, e.g. when
  inductor specialised a Python float input such as a norm's ``eps``; not a recompile);
* ``recompiles``: graphs compiled by the calls at the other voxel counts (0: none), the counts including
  64 and 80, equal to the channels and to the finest level's width;
* ``compiled_ms`` / ``eager_ms`` / ``static_ms``: the median steady-state call of the compiled module,
  of the eager module (the default CPU plans) and of the eager static-shape path (``static_path()``,
  the static-shape formulation exporters capture), the three interleaved call by call, and the ratio
  eager / compiled, at the middle voxel count or at each of ``--timed``.

A first call's time depends on inductor's on-disk cache (``TORCHINDUCTOR_CACHE_DIR``): run the script twice
for the warm figure.

Run: ``python benchmarks/compile.py [--threads 1] [--backend inductor] [--cases MSDFF SFF "FusionBlock(MSDFF)" README]
[--timed 2000 8000] [--json out.json]`` (default: MSDFF only). The machine
this was written on is shared: the figures in docs/performance.md are a single run.
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
import _readme_block  # noqa: E402
from _common import print_table, write_json  # noqa: E402

from mssf_blocks import MSDFF, SFF, FusionBlock, FusionInputs, QueryInit, SparseVoxels, static_path  # noqa: E402
from mssf_blocks import torch_versions as _compat  # noqa: E402
from mssf_blocks.geometry import CentroidProjection  # noqa: E402

RANGE = (0.0, -25.6, -3.0, 51.2, 25.6, 2.0)
GRID = (10, 128, 128)  # (D, H, W) voxels of 0.4 x 0.4 x 0.5 m
IMAGE = (384, 640)
C_VOX, C_IMG = 64, 64


def _frame(n: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    d, h, w = GRID
    idx = torch.randperm(d * h * w, generator=g)[:n]
    coords = torch.stack([torch.zeros(n, dtype=torch.long), idx // (h * w), idx // w % h, idx % w], 1).int()
    vox = SparseVoxels(torch.randn(n, C_VOX, generator=g), coords, GRID, 1, voxel_size=(0.4, 0.4, 0.5), point_range_min=RANGE[:3])
    pts = torch.rand(4 * n, 3, generator=g) * torch.tensor([51.2, 51.2, 5.0]) + torch.tensor(RANGE[:3])
    # a forward-looking pinhole camera at the origin (x forward): u = 320 - 320 y / x, v = 192 - 320 z / x
    l2i = torch.tensor([[[320.0, -320.0, 0.0, 0.0], [192.0, 0.0, -320.0, 0.0], [1.0, 0.0, 0.0, 0.0]]])
    feats = [torch.randn(1, C_IMG, IMAGE[0] // s, IMAGE[1] // s, generator=g) for s in (8, 16, 32, 64)]
    inputs = FusionInputs(feats, l2i, IMAGE, pts, torch.zeros(4 * n, dtype=torch.long))
    uv = torch.rand(n, 1, 2, generator=g)
    valid = torch.ones(n, 1, dtype=torch.bool)
    proj = CentroidProjection(uv, valid.float(), valid, torch.zeros(n, 3), valid[:, 0], vox.batch_index)
    return vox, inputs, proj


def _cases():
    def sff():
        m = SFF([C_IMG] * 4, C_VOX)
        return m, lambda mod, vox, inp, proj: mod(inp.image_features, proj)

    def msdff():
        m = MSDFF(C_IMG, C_VOX, num_heads=8, num_levels=4, num_points=4)
        return m, lambda mod, vox, inp, proj: mod(vox.features, inp.image_features, proj)

    def block():
        m = FusionBlock(MSDFF(C_IMG, C_VOX, num_heads=8, num_levels=4, num_points=4),
                        query_init=QueryInit(C_VOX, C_IMG, C_VOX, RANGE))
        return m, lambda mod, vox, inp, proj: mod(vox, inp).features

    def readme():
        return _readme_block.build(), lambda mod, vox, inp, proj: mod(vox, inp).features

    return {"SFF": sff, "MSDFF": msdff, "FusionBlock(MSDFF)": block, "README": readme}


def _print_breakdown(name: str, train: bool, compile_s: float) -> None:
    """The first call's time by phase (dynamo's own timers: tracing, AOT autograd, inductor's codegen,
    the C++ build), the largest first; phases nest, so they do not add up to ``compile_s``."""
    from torch._dynamo.utils import compilation_time_metrics

    totals = sorted(((sum(v), len(v), k) for k, v in compilation_time_metrics.items()), reverse=True)
    compilation_time_metrics.clear()  # (the next case's first call counts its own)
    print(f"{name} {'train' if train else 'eval'}: first call {compile_s:.1f} s; phases (s, nested):")
    for total, calls, key in totals[:14]:
        print(f"  {total:8.2f}  {key} ({calls} call{'s' if calls > 1 else ''})")


def _interleaved(fns, repeats: int):
    """Median wall time of each of ``fns`` after one warm-up call each, the calls interleaved round by
    round (on a shared machine a drift of the load then weighs on every one alike), each round starting
    one call later (the call after the static path's, which frees large buffers, is not always the same)."""
    for fn in fns:
        fn()
    times = [[] for _ in fns]
    for r in range(repeats):
        for i in range(len(fns)):
            k = (r + i) % len(fns)
            t0 = time.perf_counter()
            fns[k]()
            times[k].append(time.perf_counter() - t0)
    return [statistics.median(t) for t in times]


def _call(run, mod, frame, train: bool):
    vox, inp, proj = frame
    if not train:
        with torch.no_grad():
            return run(mod, vox, inp, proj)
    vox = vox.replace(features=vox.features.detach().requires_grad_())
    out = run(mod, vox, inp, proj)
    out.sum().backward()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--backend", default="inductor")
    # 64 and 80 equal a channel count and a level's width: with duck sizing, a voxel count equal to another
    # size of the first call's inputs shares its symbol, and a later count that differs recompiles
    ap.add_argument("--voxels", type=int, nargs="+", default=[2000, 2600, 3300, 4100, 5000, 64, 80])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--timed", type=int, nargs="+", default=None,
                    help="voxel counts timed (compiled, eager, static interleaved); default: the middle of --voxels")
    ap.add_argument("--cases", nargs="+", default=["MSDFF"],
                    help="of SFF, MSDFF, 'FusionBlock(MSDFF)', README (README.md's example at its widths); each "
                         "costs two inductor compiles, ~5 min each at load average 10")
    ap.add_argument("--json", default=None)
    ap.add_argument("--specialize-floats", action="store_true",
                    help="torch._dynamo.config.specialize_float = True: Python float inputs (voxel sizes, the point "
                         "range, norm eps) become constants instead of symbols that inductor's float pass "
                         "specialises later, restarting the whole trace once")
    ap.add_argument("--breakdown", action="store_true",
                    help="print where each first call's time went (dynamo's per-phase compile times)")
    args = ap.parse_args()
    _compat.require("compile_dynamic", "benchmarks/compile.py")
    torch.set_num_threads(args.threads)
    if args.specialize_floats:
        torch._dynamo.config.specialize_float = True
    rows = []
    for name, build in _cases().items():
        if args.cases and name not in args.cases:
            continue
        make = _readme_block.frame if name == "README" else _frame
        frames = [make(n, seed=i) for i, n in enumerate(args.voxels)]
        timed = [make(n, seed=100 + i) for i, n in enumerate(args.timed)] if args.timed else [frames[len(frames) // 2]]
        for train in (False, True):
            torch.manual_seed(0)
            base, run = build()
            base.train(train)
            torch._dynamo.reset()
            graphs = []  # one entry per (re)compilation
            inner = torch._dynamo.lookup_backend(args.backend)

            def counting(gm, example_inputs):
                graphs.append(1)
                return inner(gm, example_inputs)

            compiled = torch.compile(run, fullgraph=True, dynamic=True, backend=counting)
            mod = copy.deepcopy(base)
            t0 = time.perf_counter()
            _call(compiled, mod, frames[0], train)
            compile_s = time.perf_counter() - t0
            first_graphs = len(graphs)
            if args.breakdown:
                _print_breakdown(name, train, compile_s)
            new_sizes = []
            for f in frames[1:]:
                t0 = time.perf_counter()
                _call(compiled, mod, f, train)
                new_sizes.append(time.perf_counter() - t0)
            new_sizes.sort()
            eager_mod = copy.deepcopy(base)
            for mid in timed:
                def static_call(mid=mid):
                    with static_path():
                        return _call(run, eager_mod, mid, train)

                comp, eager, static = _interleaved([lambda mid=mid: _call(compiled, mod, mid, train),
                                                    lambda mid=mid: _call(run, eager_mod, mid, train), static_call],
                                                   args.repeats)
                rows.append({
                    "module": name, "mode": "fwd+bwd train" if train else "fwd eval", "N": mid[0].num_voxels,
                    "compile_s": round(compile_s, 1), "new_sizes_s": round(new_sizes[len(new_sizes) // 2], 3),
                    "compiled_ms": round(1e3 * comp, 1), "eager_ms": round(1e3 * eager, 1),
                    "static_ms": round(1e3 * static, 1), "eager/compiled": round(eager / comp, 2),
                    "first_graphs": first_graphs, "recompiles": len(graphs) - first_graphs,
                    "voxel_counts": len(frames) + len(args.timed or []), "load": round(os.getloadavg()[0], 1),
                })
                print(rows[-1], flush=True)
    print_table(rows, list(rows[0]) if rows else [])
    if args.json:
        write_json(args.json, {"threads": args.threads, "backend": args.backend, "torch": torch.__version__,
                               "rows": rows})


if __name__ == "__main__":
    main()
