"""Export MSSF-PointPillars (pure torch) to ONNX and check it in onnxruntime against PyTorch.

    python examples/export_onnx.py --out mssf_pointpillars.onnx [--fusion msdff|sff] [--blocks 2]
        [--preset tiny|vod] [--opset 18]

Builds the detector (random weights, eval mode), voxelises three generated scenes with different point,
pillar and voxel counts, exports :class:`mssf_examples.models.export.PointPillarsGraph` with
``torch.onnx.export(dynamo=True)`` (those counts as dynamic axes), runs the ONNX model in onnxruntime on
all three and prints the largest absolute difference to the eager PyTorch detector's head outputs
(``MSSFDetector.extract``, the default CPU plans). Exits non-zero above ``--tolerance`` (1e-4).
Needs ``onnx``, ``onnxscript`` and ``onnxruntime`` (the ``dev`` extra). See docs/deployment.md.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mssf_blocks.torch_versions import require  # noqa: E402
from mssf_examples.data.batch import RadarCameraBatch  # noqa: E402
from mssf_examples.models.detectors import build_detector  # noqa: E402
from mssf_examples.models.export import PointPillarsGraph, graph_dynamic_shapes, graph_inputs, input_names  # noqa: E402
from mssf_examples.models.presets import TINY, VOD  # noqa: E402


def generated_scene(preset, seed: int, num_points: int) -> RadarCameraBatch:
    """One frame: radar points clustered on a few objects plus clutter, a random image, a pinhole camera."""
    g = torch.Generator().manual_seed(seed)
    x0, y0, z0, x1, y1, z1 = preset.pillar_range
    k = max(1, num_points // 40)  # objects
    centres = torch.rand(k, 3, generator=g) * torch.tensor([x1 - x0, y1 - y0, z1 - z0]) * 0.8 + torch.tensor(
        [x0 + 0.1 * (x1 - x0), y0 + 0.1 * (y1 - y0), z0 + 0.1 * (z1 - z0)])
    on_objects = centres[torch.randint(0, k, (num_points * 3 // 4,), generator=g)]
    on_objects = on_objects + torch.randn(on_objects.shape, generator=g) * torch.tensor([0.8, 0.8, 0.3])
    clutter = torch.rand(num_points - on_objects.shape[0], 3, generator=g) * torch.tensor(
        [x1 - x0 + 2, y1 - y0 + 2, z1 - z0]) + torch.tensor([x0 - 1, y0 - 1, z0])  # some outside the range
    xyz = torch.cat([on_objects, clutter])
    extra = torch.randn(xyz.shape[0], preset.num_point_features - 3, generator=g)
    h, w = preset.image_size
    f = w / (2 * math.tan(math.radians(35)))  # 70 degree horizontal field of view, camera at the origin along +x
    l2i = torch.tensor([[[w / 2, -f, 0.0, 0.0], [h / 2, 0.0, -f, 0.0], [1.0, 0.0, 0.0, 0.0]]])[None]
    return RadarCameraBatch(points=[torch.cat([xyz, extra], 1)], lidar2img=l2i,
                            images=torch.rand(1, 1, 3, h, w, generator=g))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="mssf_pointpillars.onnx")
    ap.add_argument("--fusion", choices=("msdff", "sff"), default="msdff")
    ap.add_argument("--blocks", type=int, default=2, help="fusion blocks (0-3)")
    ap.add_argument("--preset", choices=("tiny", "vod"), default="tiny")
    ap.add_argument("--opset", type=int, default=18, help=">= 16 (GridSample); 18 for ScatterElements max")
    ap.add_argument("--points", type=int, nargs=3, default=(150, 260, 400), help="points of the 3 scenes")
    ap.add_argument("--tolerance", type=float, default=1e-4)
    args = ap.parse_args(argv)
    require("onnx_dynamo", "export_onnx.py")  # (torch-version dependent: mssf_blocks.torch_versions)
    import onnxruntime as ort

    preset = TINY if args.preset == "tiny" else VOD
    torch.manual_seed(0)
    det = build_detector("pointpillars", preset, num_fusion_blocks=args.blocks, fusion=args.fusion).eval()
    scenes = [generated_scene(preset, seed, n) for seed, n in enumerate(args.points)]
    graph = PointPillarsGraph(det, preset.image_size).eval()
    example = graph_inputs(det, scenes[0])
    t0 = time.perf_counter()
    with torch.no_grad():
        program = torch.onnx.export(graph, example, dynamic_shapes=graph_dynamic_shapes(det), dynamo=True,
                                    opset_version=args.opset, input_names=input_names(det), verbose=False)
    program.save(args.out)
    print(f"exported {args.out} (opset {args.opset}) in {time.perf_counter() - t0:.1f} s")
    session = ort.InferenceSession(args.out, providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    worst = 0.0
    for scene in scenes:
        inputs = graph_inputs(det, scene)
        flat = [t for x in inputs for t in (x if isinstance(x, list) else [x])]
        if len(flat) != len(names):
            raise SystemExit(f"internal error: {len(flat)} tensors for {len(names)} ONNX inputs {names}")
        outputs = session.run(None, {n: t.numpy() for n, t in zip(names, flat)})
        with torch.no_grad():
            ref, out, _, _ = det.extract(scene)
        keys = list(ref)
        diff = max(float((torch.from_numpy(o) - ref[k]).abs().max()) for o, k in zip(outputs, keys))
        worst = max(worst, diff)
        print(f"points {inputs[0].shape[0]}, pillars {inputs[4].shape[0]}, lift voxels "
              f"{[c.shape[0] for c in inputs[5]]}: max |onnxruntime - torch| = {diff:.2e}")
    ok = worst <= args.tolerance
    print(f"{'OK' if ok else 'FAILED'}: max abs difference {worst:.2e} (tolerance {args.tolerance:g})")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
