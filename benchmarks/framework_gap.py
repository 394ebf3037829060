"""Benchmark: the fusion gap inside the real frameworks - MSSF and its radar-only twin trained by mmdetection3d's
own runner and by OpenPCDet's own ``train.py`` on the demo's generated scenes at the demo's budget.

``make demo`` trains MSSF-PointPillars and its radar-only twin with the library's own loop and measures the
fusion gap with the official VoD protocol. This script asks whether the same kind of gap appears when the
frameworks do the training (their data pipelines, samplers, optimisers, schedules, heads, losses, evaluation):

1. the demo's scenes (same generator, seed and counts: 400 train / 80 val), written as a VoD release tree at
   the camera's full resolution (``_gap_data.py``: what a framework reads);
2. the demo's image branch (ResNet-18, 8 base channels, 16-channel FPN), pre-trained the demo's way on the
   train scenes' 2D semantics, saved as an mmdet checkpoint and loaded frozen by both frameworks;
3. mmdetection3d 1.4: ``examples/configs/mmdet3d/mssf_pointpillars_vod.py`` and ``pointpillars_vod_radar.py``
   sized as the demo's model (``_gap_mmdet3d.py``), ``Runner.train()`` for the demo's steps, the VoD metric;
4. OpenPCDet: ``examples/configs/openpcdet/vod_models/mssf_voxelnext.yaml`` and ``voxelnext_radar.yaml`` sized as
   the demo's voxel model (``_gap_openpcdet.py``), OpenPCDet's ``tools/train.py`` through
   ``python -m mssf_examples.openpcdet --cpu`` for the demo's budget, then the VoD evaluation of its last
   checkpoint;

and prints the paper-style table of both pairs (AP3D R11 and R40 over the entire annotated area and the
driving corridor) with the gap ``MSSF - radar only`` per framework. ``metrics.json`` in ``--out`` keeps
every value, the configuration and the wall times. Target (issue 44): a gap of the demo's kind, >= +5 mAP
(AP3D R11, entire area), in each framework.

Usage: ``python benchmarks/framework_gap.py [--frameworks mmdet3d openpcdet] [--steps 2000]
[--train-scenes 400] [--val-scenes 80] [--out outputs/framework_gap] [--smoke]`` (``make bench-framework_gap``).
``--smoke`` is a few steps on a few small scenes: it checks the whole path (tests/benchmarks), no figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import torch  # noqa: E402

FRAMEWORKS = ("mmdet3d", "openpcdet")
KEY = "VoD/entire_area/mAP/AP3D_R11"


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frameworks", nargs="+", choices=FRAMEWORKS, default=list(FRAMEWORKS))
    ap.add_argument("--steps", type=int, default=2000, help="training steps per model (the demo's 2000)")
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--lr", type=float, default=3e-3, help="one-cycle peak learning rate (the demo's)")
    ap.add_argument("--train-scenes", type=int, default=400)
    ap.add_argument("--val-scenes", type=int, default=80)
    ap.add_argument("--image-pretrain-steps", type=int, default=1000)
    ap.add_argument("--fusion-blocks", type=int, default=1, help="n of the fusion models (the demo's 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1, help="data-loader workers of the frameworks")
    ap.add_argument("--openpcdet", type=Path, default=None,
                    help="an OpenPCDet clone (default: ../shared/thirdparty's archive, unpacked into --out)")
    ap.add_argument("--out", type=Path, default=ROOT / "outputs" / "framework_gap")
    ap.add_argument("--smoke", action="store_true", help="a few steps on a few small scenes (checks the path)")
    args = ap.parse_args(argv)
    if args.smoke:
        # one epoch of 4 steps: OpenPCDet's one-cycle schedule divides by its warm-up length (0 below 3 steps)
        args.steps, args.train_scenes, args.val_scenes, args.image_pretrain_steps = 4, 4, 2, 2
        args.batch_size = 1
    for name in ("steps", "batch_size", "train_scenes", "val_scenes", "image_pretrain_steps", "fusion_blocks"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')}: expected a positive int, got {getattr(args, name)}")
    if args.batch_size > args.train_scenes:
        ap.error(f"--batch-size ({args.batch_size}) must be <= --train-scenes ({args.train_scenes})")
    if args.workers < 0:
        ap.error(f"--workers: expected >= 0, got {args.workers}")
    return args


def _bar(it, desc):
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is in the examples extra
        return it
    return tqdm(it, desc=desc, unit="scene", dynamic_ncols=True)


def prepare(args):
    """Scenes, the full-resolution tree and the pre-trained image branch (steps 1 and 2)."""
    from demo_steps import demo_preset
    from _gap_data import save_image_checkpoint, write_full_resolution_tree
    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.scenes.synthetic import CLASS_NAMES, SceneConfig, SyntheticDataset
    from mssf_examples.training.image_pretrain import pretrain_image_branch

    scene_cfg = SceneConfig(image_size=(64, 104)) if args.smoke else SceneConfig()
    preset = demo_preset(scene_cfg, args.smoke)
    splits = {"train": SyntheticDataset("train", args.train_scenes, scene_cfg, seed=args.seed),
              "val": SyntheticDataset("val", args.val_scenes, scene_cfg, seed=args.seed)}
    train_scenes = [splits["train"][i] for i in _bar(range(len(splits["train"])), "scenes train")]
    tree = args.out / "view_of_delft"
    write_full_resolution_tree(tree, {"train": train_scenes, "val": splits["val"]}, scene_cfg,
                               progress=lambda it, split: _bar(it, f"VoD tree {split}"))
    torch.manual_seed(args.seed)
    branch = ImageBranch(preset.image_depth, preset.image_base_channels, preset.fpn_channels, preset.num_image_levels)
    log = pretrain_image_branch(branch, train_scenes, args.image_pretrain_steps, batch_size=min(8, len(train_scenes)),
                                lr=3e-3, seed=args.seed, num_classes=len(CLASS_NAMES))
    ckpt = save_image_checkpoint(branch, args.out / "image_branch.pth")
    return scene_cfg, preset, tree, ckpt, {"image_pretrain_seconds": log["seconds"]}


def run_mmdet3d(args, scene_cfg, preset, tree, ckpt):
    from _gap_mmdet3d import MODELS, demo_sized_config, train_and_evaluate
    from mssf_examples.mmdet3d.infos import create_vod_infos

    create_vod_infos(tree, "radar_5frames", ("train", "val"))
    budget = dict(steps=args.steps, batch_size=args.batch_size, lr=args.lr, seed=args.seed, workers=args.workers,
                  fusion_blocks=args.fusion_blocks, image_size=tuple(scene_cfg.image_size))
    out = {}
    for model, name in MODELS.items():
        t0 = time.perf_counter()
        cfg = demo_sized_config(name, tree / "radar_5frames", args.out / "mmdet3d" / Path(name).stem, preset, budget,
                                ckpt)
        metrics = train_and_evaluate(cfg)
        out[model] = {"config": f"examples/configs/mmdet3d/{name}", "metrics": metrics,
                      "seconds": time.perf_counter() - t0}
    return out


def table(results) -> str:
    lines = [f"{'framework':<10} {'model':<28} {'entire R11':>10} {'entire R40':>10} {'corridor R11':>12}"]
    for fw, models in results.items():
        for model, r in models.items():
            m = r["metrics"]
            lines.append(f"{fw:<10} {model:<28} {m.get(KEY, float('nan')):>10.2f} "
                         f"{m.get('VoD/entire_area/mAP/AP3D_R40', float('nan')):>10.2f} "
                         f"{m.get('VoD/driving_corridor/mAP/AP3D_R11', float('nan')):>12.2f}")
        vals = [r["metrics"].get(KEY, float("nan")) for r in models.values()]
        if len(vals) == 2:
            lines.append(f"{fw:<10} {'gap (MSSF - radar only)':<28} {vals[0] - vals[1]:>+10.2f}")
    return "\n".join(lines)


def main(argv=None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene_cfg, preset, tree, ckpt, timings = prepare(args)
    timings["prepare_seconds"] = time.perf_counter() - t0
    results = {}
    if "mmdet3d" in args.frameworks:
        results["mmdet3d"] = run_mmdet3d(args, scene_cfg, preset, tree, ckpt)
    if "openpcdet" in args.frameworks:
        from _gap_openpcdet import run_openpcdet

        results["openpcdet"] = run_openpcdet(args, scene_cfg, preset, tree, ckpt)
    timings["total_seconds"] = time.perf_counter() - t0
    text = table(results)
    print(text)
    gaps = {fw: list(m.values())[0]["metrics"].get(KEY, float("nan")) - list(m.values())[1]["metrics"].get(KEY, float("nan"))
            for fw, m in results.items() if len(m) == 2}
    report = {"results": results, "gap_AP3D_R11_entire_area": gaps, "table": text, "timings": timings,
              "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
              "environment": {"python": platform.python_version(), "torch": torch.__version__,
                              "cpu": platform.processor() or platform.machine()}}
    (args.out / "metrics.json").write_text(json.dumps(report, indent=1, default=str))
    print(f"written: {args.out / 'metrics.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
