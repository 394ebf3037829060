"""Benchmark: the static-shape path (what a deployment runs) against the eager path it comes from.

Three ways to run the same module on the same inputs, timed in interleaved rounds in one process, one
thread (``torch.set_num_threads(1)``; onnxruntime with one intra-op and one inter-op thread):

* ``eager``: the module as trained (the default CPU plans: per level the cheapest exact "touched" plan);
* ``static``: the same module under :func:`mssf_blocks.static_path` (the static-shape path that
  ``torch.export`` and other graph captures take: MSDFF samples the raw channels of every bilinear corner
  with fixed-size embedding bags and projects per head, ``bag.sample_project_static``);
* ``exported``: ``torch.onnx.export(dynamo=True)`` of the module (voxel count a dynamic axis; MSDFF's ONNX
  form is project-first with a 1 x 1 ``Conv`` and ``GridSample``, see ``docs/deployment.md``) run in
  onnxruntime on the CPU, given NCHW copies of the levels (ONNX tensors have no strides; the copy is
  made before the timing).

Cases. MSDFF at the paper's width (256 image channels, ``value_proj`` 256 -> 256, 8 heads, 4 levels,
4 points; 64 voxel channels) on a View-of-Delft image (1216 x 1936, FPN strides 4, 8, 16, 32: levels
304 x 484 to 38 x 61), N = 2,500 and 8,000 voxels, every voxel seen by the camera, projections uniform over
the radar band (``u`` in [0.06, 0.85], ``v`` in [0.49, 0.89], as ``benchmarks/msdff.py``); image levels in
channels-last memory (what the examples' ``ImageBranch`` returns) and in NCHW (what an ONNX graph holds).
And the whole MSSF-PointPillars (VoD preset, two MSDFF fusion blocks, precomputed image features as
``benchmarks/detectors.py``'s frame, the paper's frozen image branch) as
:class:`~mssf_examples.models.export.PointPillarsGraph` (pre-voxelised inputs, head outputs) eager vs
exported (and static).

Times: process CPU time (``time.process_time``: with one thread the work done, robust to the other
processes of a shared machine), median over ``--repeats`` rounds after a warm-up call; the ratios are
ratios of the medians, with the lowest and highest per-round ratio beside them. Each case also checks that
the three agree (max abs difference to eager).

Usage: ``python benchmarks/static_path.py [--repeats 5] [--voxels 2500 8000] [--no-detector] [--smoke]
[--json out.json]``; ``--smoke``: tiny sizes, one fusion block, one round (seconds;
tests/project/test_bench_static_path.py runs it). ``--block-mib 2 4 8 16 0``: only the static MSDFF with its
queries bagged in blocks of each size (0: one block), the measurement behind ``plan_costs._STATIC_BLOCK_BYTES``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
from _common import print_table, round_spread, write_json  # noqa: E402

from mssf_blocks import MSDFF, static_path  # noqa: E402
from mssf_blocks.geometry import CentroidProjection  # noqa: E402

PAPER = dict(image=(1216, 1936), strides=(4, 8, 16, 32), channels=256, heads=8, points=4, voxel_channels=64)
SMOKE = dict(image=(48, 80), strides=(4, 8), channels=16, heads=2, points=2, voxel_channels=8)


class MSDFFGraph(nn.Module):
    """MSDFF with tensor inputs (what an exporter takes): ``query (N, E)``, ``uv (N, 1, 2)``, ``valid (N, 1)``,
    ``batch_index (N,)`` and the list of levels."""

    def __init__(self, msdff: MSDFF) -> None:
        super().__init__()
        self.msdff = msdff

    def forward(self, query, uv, valid, batch_index, levels):
        n = query.shape[0]
        proj = CentroidProjection(uv, valid.to(uv.dtype), valid, uv.new_zeros(n, 3), valid[:, 0], batch_index)
        return self.msdff(query, list(levels), proj)


def msdff_inputs(cfg, n: int, channels_last: bool, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    h, w = cfg["image"]
    levels = [torch.randn(1, cfg["channels"], math.ceil(h / s), math.ceil(w / s), generator=g) for s in cfg["strides"]]
    if channels_last:
        levels = [lv.contiguous(memory_format=torch.channels_last) for lv in levels]
    uv = torch.rand(n, 1, 2, generator=g) * torch.tensor([0.79, 0.40]) + torch.tensor([0.06, 0.49])
    return (torch.randn(n, cfg["voxel_channels"], generator=g), uv, torch.ones(n, 1, dtype=torch.bool),
            torch.zeros(n, dtype=torch.long), levels)


def ort_session(module: nn.Module, example, dynamic_shapes, path: str):
    """``torch.onnx.export(dynamo=True)`` of ``module`` (eval, no grad), loaded in onnxruntime on one thread."""
    import onnxruntime as ort

    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        program = torch.onnx.export(module, example, dynamic_shapes=dynamic_shapes, dynamo=True, opset_version=18,
                                    verbose=False)
    program.save(path)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    session = ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]

    def run(*args):
        flat = [t for t in torch.utils._pytree.tree_leaves(args) if isinstance(t, torch.Tensor)]
        if len(flat) != len(names):
            raise SystemExit(f"internal error: {len(flat)} tensors for {len(names)} ONNX inputs {names}")
        return session.run(None, {k: t.contiguous().numpy() for k, t in zip(names, flat)})[0]

    return run


def interleaved(paths, repeats: int):
    """``{name: [seconds per round]}``: one call of every path per round (process CPU time), after a warm-up."""
    for fn in paths.values():
        fn()
    times = {k: [] for k in paths}
    for _ in range(repeats):
        for k, fn in paths.items():
            t0 = time.process_time()
            fn()
            times[k].append(time.process_time() - t0)
    return times


def ratios_row(label, times, outputs, base="eager"):
    row = {"case": label}
    ref = torch.as_tensor(outputs[base])
    for k, ts in times.items():
        row[f"{k} ms"] = statistics.median(ts) * 1e3
        if k != base:
            row[f"{k} / {base}"] = statistics.median(ts) / statistics.median(times[base])
            row[f"{k} rounds"] = round_spread(ts, times[base])
            row[f"{k} max diff"] = f"{float((torch.as_tensor(outputs[k]) - ref).abs().max()):.1e}"
    return row


def floors_row(label, eager_ms, run_static, repeats, onnx=None):
    """``(row, ONNX floor)``: the floors of ``_static_floors`` at this case, against eager; ``onnx``: the ONNX floor
    already measured on the same values in the other layout (ONNX tensors have no strides: the same graphs)."""
    from _static_floors import capture_static_sampling, onnx_floor, torch_floor

    args = capture_static_sampling(run_static)
    with torch.no_grad():
        static_total = statistics.median(interleaved({"static": run_static}, repeats)["static"])
    tf, of = torch_floor(args, repeats), onnx or onnx_floor(args, repeats)
    static_floor = static_total - tf["sampling"] + tf["floor"]
    return {"case": label, "eager ms": eager_ms, "static ms": static_total * 1e3,
            "static floor ms": static_floor * 1e3, "static floor / eager": static_floor * 1e3 / eager_ms,
            "ONNX floor ms": of["floor"] * 1e3, "ONNX floor / eager": of["floor"] * 1e3 / eager_ms,
            "static levels (raw / projected) ms": " ".join(f"{r * 1e3:.1f}/{p * 1e3:.1f}" for r, p in tf["levels"]),
            "ONNX levels (Conv / Gather / GridSample) ms": " ".join(
                "/".join(f"{t * 1e3:.1f}" for t in lv) for lv in of["levels"])}, of


def msdff_graph(cfg) -> MSDFFGraph:
    """The benchmark's MSDFF (seed 0) as a graph module, eval."""
    torch.manual_seed(0)
    msdff = MSDFF(cfg["channels"], cfg["voxel_channels"], num_heads=cfg["heads"], num_levels=len(cfg["strides"]),
                  num_points=cfg["points"]).eval()
    with torch.no_grad():  # query-dependent offsets and weights, as after training
        msdff.sampling_offsets.weight.normal_(0, 0.5)
        msdff.attention_weights.weight.normal_(0, 0.1)
    return MSDFFGraph(msdff).eval()


def bench_msdff(cfg, voxels, repeats, tmp, floors=None):
    graph = msdff_graph(cfg)
    from torch.export import Dim

    n_dim = Dim("N", min=2)
    dynamic = ({0: n_dim}, {0: n_dim}, {0: n_dim}, {0: n_dim}, [None] * len(cfg["strides"]))
    exported = ort_session(graph, msdff_inputs(cfg, 64, False), dynamic, os.path.join(tmp, "msdff.onnx"))
    rows = []
    for n in voxels:
        onnx = None  # (the ONNX floor of this voxel count, measured on the channels-last case)
        for layout in ("channels-last", "NCHW"):
            args = msdff_inputs(cfg, n, layout == "channels-last", seed=n)
            nchw = args[:4] + ([lv.contiguous() for lv in args[4]],)  # (an ONNX graph's layout; copied untimed)

            def static(args=args):
                with static_path():
                    return graph(*args)

            paths = {"eager": lambda args=args: graph(*args), "static": static,
                     "exported": lambda nchw=nchw: exported(*nchw)}
            with torch.no_grad():
                outputs = {k: fn() for k, fn in paths.items()}
                times = interleaved(paths, repeats)
            rows.append(ratios_row(f"MSDFF N={n} {layout}", times, outputs))
            if floors is not None:
                row, onnx = floors_row(f"MSDFF N={n} {layout}", rows[-1]["eager ms"], static, repeats, onnx)
                floors.append(row)
    return rows


def bench_block_sizes(cfg, voxels, mibs, repeats):
    """The static MSDFF (channels-last levels) with its queries bagged in blocks of each of ``mibs`` MiB of raw
    samples (0: one block of every query), against eager, interleaved: the measurement behind
    ``plan_costs._STATIC_BLOCK_BYTES``."""
    from mssf_blocks.functional.deform import bag

    graph = msdff_graph(cfg)
    default = bag._STATIC_BLOCK_BYTES
    rows = []
    for n in voxels:
        args = msdff_inputs(cfg, n, True, seed=n)

        def static(mib, args=args):
            bag._STATIC_BLOCK_BYTES = (mib << 20) if mib else 1 << 62
            try:
                with static_path():
                    return graph(*args)
            finally:
                bag._STATIC_BLOCK_BYTES = default

        paths = {"eager": lambda args=args: graph(*args)}
        paths.update({f"{mib} MiB" if mib else "one block": lambda mib=mib: static(mib) for mib in mibs})
        with torch.no_grad():
            times = interleaved(paths, repeats)
        row = {"case": f"MSDFF N={n} channels-last", "eager ms": statistics.median(times["eager"]) * 1e3}
        for k, ts in times.items():
            if k != "eager":
                row[f"{k} / eager"] = statistics.median(ts) / statistics.median(times["eager"])
        rows.append(row)
    return rows


def bench_detector(smoke: bool, points: int, repeats: int, tmp, blocks: int = 2):
    from mssf_examples.data.batch import RadarCameraBatch
    from mssf_examples.models.detectors import build_detector
    from mssf_examples.models.export import PointPillarsGraph, graph_dynamic_shapes, graph_inputs
    from mssf_examples.models.presets import TINY, VOD

    from detectors import vod_frame  # this folder: the VoD-sized frame of benchmarks/detectors.py

    preset = TINY if smoke else VOD
    torch.manual_seed(0)
    det = build_detector("pointpillars", preset, num_fusion_blocks=min(blocks, 1) if smoke else blocks,
                         fusion="msdff", image_features="precomputed").eval()
    if smoke:  # a generated scene of the tiny preset, with random precomputed levels
        from export_onnx import generated_scene  # examples/export_onnx.py

        scene = generated_scene(preset, 0, points)
        h, w = preset.image_size
        g = torch.Generator().manual_seed(0)
        levels = [torch.randn(1, 1, preset.fpn_channels, math.ceil(h / s), math.ceil(w / s), generator=g)
                  for s in (4, 8, 16, 32, 64)[: preset.num_image_levels]]
        frame = RadarCameraBatch(points=scene.points, lidar2img=scene.lidar2img, image_features=levels,
                                 image_size=(h, w))
    else:
        frame = vod_frame(points, channels_last=True)
    graph = PointPillarsGraph(det, frame.image_size).eval()
    inputs = graph_inputs(det, frame)
    nchw = inputs[:6] + ([lv.contiguous() for lv in inputs[6]],) + inputs[7:]
    dyn = graph_dynamic_shapes(det, len(inputs[6]))
    exported = ort_session(graph, nchw, dyn, os.path.join(tmp, "pointpillars.onnx"))

    def static():
        with static_path():
            return graph(*inputs)["cls"]

    paths = {"eager": lambda: graph(*inputs)["cls"], "static": static, "exported": lambda: exported(*nchw)}
    with torch.no_grad():
        outputs = {k: fn() for k, fn in paths.items()}
        times = interleaved(paths, repeats)
    voxels = [int(c.shape[0]) for c in inputs[5]]
    label = "tiny preset" if smoke else "VoD"
    if not blocks:  # the radar-only twin: what the exported graph costs without any fusion
        return [ratios_row(f"radar-only PointPillars (the twin) {label}, {points} points", times, outputs)]
    return [ratios_row(f"MSSF-PointPillars {label}, {points} points, lift voxels {voxels}", times, outputs)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--voxels", type=int, nargs="+", default=[2500, 8000])
    ap.add_argument("--points", type=int, default=2500, help="radar points of the detector's frame")
    ap.add_argument("--no-detector", action="store_true")
    ap.add_argument("--no-floors", action="store_true", help="skip the floors (benchmarks/_static_floors.py)")
    ap.add_argument("--smoke", action="store_true", help="tiny sizes, one round: checks that the script runs")
    ap.add_argument("--block-mib", type=int, nargs="+", default=None,
                    help="only time the static MSDFF with blocks of these many MiB of raw samples (0: one block)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    cfg = SMOKE if args.smoke else PAPER
    voxels = [40, 70] if args.smoke else args.voxels
    repeats = 1 if args.smoke else args.repeats
    if args.block_mib:
        rows = bench_block_sizes(cfg, voxels, args.block_mib, repeats)
        print_table(rows, list(rows[0]))
        if args.json:
            write_json(args.json, rows)
        return 0
    floors = None if args.no_floors else []
    with tempfile.TemporaryDirectory() as tmp:
        rows = bench_msdff(cfg, voxels, repeats, tmp, floors)
        if not args.no_detector:
            for blocks in (2, 0):
                rows += bench_detector(args.smoke, 200 if args.smoke else args.points, repeats, tmp, blocks)
    columns = ["case", "eager ms", "static ms", "exported ms", "static / eager", "static rounds",
               "exported / eager", "exported rounds", "static max diff", "exported max diff"]
    print_table(rows, columns)
    if floors:
        print("\nFloors of any exact static-shape sampling (benchmarks/_static_floors.py; the ONNX floor measured once per"
              " voxel count, on the channels-last case's values):")
        print_table(floors, list(floors[0]))
    if args.json:
        write_json(args.json, rows + (floors or []))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
