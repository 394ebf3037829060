"""Train the MSSF fusion detector and its radar-only twin on generated scenes and compare them.

The project's main demo (``make demo``). On CPU, with the same code, seed and data order for both:

1. generate ``--train-scenes`` / ``--val-scenes`` synthetic VoD-like radar + camera scenes
   (:class:`mssf_examples.scenes.synthetic.SyntheticDataset`; static clutter mimics objects on radar, the camera
   tells them apart, ghosts and leaked points give 3D-blurred points);
2. pre-train the image branch (ResNet-18 + FPN) on the train scenes' per-pixel 2D semantics with a
   linear read-out, freeze it and cache its features (:mod:`mssf_examples.training.image_pretrain`; the paper
   freezes a pre-trained image branch, and nothing can be downloaded here);
3. train ``--detector`` (default PointPillars, the cheapest) twice: with ``n = 1`` MSDFF fusion block
   plus the semantic-guided head, and with ``n = 0`` (radar only); AdamW with a one-cycle learning
   rate, as in the paper (OpenPCDet's ``adam_onecycle``: 40 % warm-up, ``div_factor`` 10);
4. evaluate both on the val split (the official VoD protocol, ``protocol="vod"``: entire annotated area
   and driving corridor, :func:`mssf_examples.evaluation.metrics.evaluate`) and print the paper-style table;
5. write ``metrics.json`` (metrics, configuration, timings) and PNG figures to ``--out``: BEV views with
   radar points, GT and predicted boxes for both models, the fusion model's semantic scores per lifted
   voxel (paper Fig. 5), the blur-ratio / foreground-recall curves (paper Fig. 7) and the image
   branch's 2D read-out.

Run: ``python examples/train_demo.py [--steps 2000] [--seed 0] [--lighting] [--out outputs/demo]``;
``--quick`` is a tiny run for tests. ``--augmentation on`` trains both models with the VoD recipe's
augmentation (:mod:`mssf_examples.data.augment`: flip with the image, rotation +-pi/4, scaling 0.95-1.05);
``--augmentation compare`` keeps the two models un-augmented and trains a third, the fusion model with
augmentation at the same budget (steps, batch, seed), to show the effect. A rerun with the same arguments gives identical metrics.
Synthetic scenes say nothing about View-of-Delft numbers; see ``docs/demo.md``.

This script parses the options, runs the stages and writes the report; the stages' building blocks
are in ``demo_steps.py`` and the figures in ``demo_figures.py`` (beside it; both re-exported here).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from demo_figures import (  # noqa: E402
    plot_bev, plot_image_semantics, plot_losses, plot_semantic_blur_curves)
from demo_steps import (  # noqa: E402
    demo_preset, ground_truths, lighting_report, predict, scene_collate, semantic_scores, train)
from mssf_blocks.diagnostics import blur_curves  # noqa: E402
from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_examples.models.detectors import DETECTOR_NAMES, build_detector  # noqa: E402
from mssf_examples.training.distributed import AMP_MODES, resolve_amp, resolve_device  # noqa: E402
from mssf_examples.evaluation.metrics import evaluate, format_table  # noqa: E402
from mssf_examples.models.image_branch import ImageBranch  # noqa: E402
from mssf_examples.training.image_pretrain import (  # noqa: E402
    SemanticReadout, precompute_features, pretrain_image_branch, segmentation_metrics)
from mssf_examples.models.presets import VOD_RECIPE  # noqa: E402
from mssf_examples.scenes.synthetic import CLASS_NAMES, SceneConfig, SyntheticDataset  # noqa: E402
from mssf_examples.models.spconv_helpers import enable_cpu_backward  # noqa: E402
from mssf_examples.training.threads import DEFAULT_THREADS  # noqa: E402

try:
    from tqdm import tqdm
except ImportError:  # pragma: no cover - tqdm is in the examples extra
    def tqdm(it=None, **kw):  # type: ignore[no-redef]
        return it

MODELS = ("MSSF (n=1)", "Radar only (n=0)")
#: The fusion model trained with augmentation (``--augmentation compare``).
AUGMENTED_MODEL = "MSSF (n=1) + augmentation"


def _finite(x):
    """JSON without NaN (null instead)."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--detector", choices=DETECTOR_NAMES, default="pointpillars")
    ap.add_argument("--steps", type=int, default=None, help="training steps per model (default 2000)")
    ap.add_argument("--epochs", type=float, default=None, help="alternative to --steps: passes over the train split")
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--lr", type=float, default=3e-3, help="one-cycle peak learning rate")
    ap.add_argument("--train-scenes", type=int, default=None, help="default 400")
    ap.add_argument("--val-scenes", type=int, default=None, help="default 80")
    ap.add_argument("--seed", type=int, default=0, help="scene seed and torch seed")
    ap.add_argument("--fusion-blocks", type=int, default=1, help="n of the fusion model")
    ap.add_argument("--fusion", choices=("msdff", "sff"), default="msdff")
    ap.add_argument("--image-branch", choices=("pretrained", "end-to-end"), default="pretrained",
                    help="pretrained: pre-train on the train scenes' 2D semantics, freeze, cache features "
                         "(the paper freezes a pre-trained branch); end-to-end: train it with the detector")
    ap.add_argument("--image-pretrain-steps", type=int, default=None, help="default 1000")
    ap.add_argument("--image-pretrain-lr", type=float, default=3e-3)
    ap.add_argument("--lighting", action="store_true", help="also report AP per lighting condition")
    ap.add_argument("--augmentation", choices=("off", "on", "compare"), default="off",
                    help="off: no augmentation; on: both models train with the VoD recipe's augmentation; "
                         "compare: also train the fusion model with it (same budget) and report both")
    ap.add_argument("--save-checkpoint", type=Path, default=None)
    ap.add_argument("--load-checkpoint", type=Path, default=None, help="skip training, evaluate these weights")
    ap.add_argument("--figure-scenes", type=int, default=3)
    ap.add_argument("--threads", type=int, default=DEFAULT_THREADS,
                    help=f"torch CPU threads (default {DEFAULT_THREADS}: see mssf_examples/training/threads.py)")
    ap.add_argument("--device", default="auto", help="auto (CUDA when available), cpu, cuda or cuda:N: where the "
                    "detectors train and predict (the image branch pre-training stays on the CPU)")
    ap.add_argument("--amp", choices=tuple(AMP_MODES), default="off",
                    help="mixed precision of the detector training (bf16 / fp16 autocast; see docs/gpus.md)")
    ap.add_argument("--quick", action="store_true", help="tiny run (a few steps and scenes) for tests")
    ap.add_argument("--out", type=Path, default=Path("outputs/demo"))
    args = ap.parse_args(argv)
    defaults = dict(image_pretrain_steps=1000, train_scenes=400, val_scenes=80)
    if args.quick:
        defaults.update(image_pretrain_steps=3, train_scenes=4, val_scenes=4, steps=3)
        args.batch_size = min(args.batch_size, 2)
        args.figure_scenes = min(args.figure_scenes, 2)
    for name, value in defaults.items():  # only unset options (0 stays 0 and is rejected below)
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.steps is None:
        per_epoch = max(args.train_scenes // args.batch_size, 1)
        args.steps = max(1, round(args.epochs * per_epoch)) if args.epochs is not None else 2000
    for name in ("steps", "batch_size", "train_scenes", "val_scenes", "threads", "image_pretrain_steps"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')}: expected a positive int, got {getattr(args, name)}")
    if args.batch_size > args.train_scenes:
        ap.error(f"--batch-size ({args.batch_size}) must be <= --train-scenes ({args.train_scenes})")
    try:
        args.device = resolve_device(args.device)
        args.amp_dtype = resolve_amp(args.amp, args.device, args.detector)
    except MSSFError as exc:
        ap.error(str(exc))
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    enable_cpu_backward()  # spconv 2.3 cannot run backward on CPU-only torch without it
    # Process-wide settings: restore them afterwards so that calling main() (e.g. from tests) leaks nothing.
    saved = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled(),
             torch.is_deterministic_algorithms_warn_only_enabled())
    torch.set_num_threads(args.threads)
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        return _run(args)
    finally:
        torch.set_num_threads(saved[0])
        torch.use_deterministic_algorithms(saved[1], warn_only=saved[2])


def _run(args) -> int:
    t_start = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)

    # --quick renders smaller images (the image branch dominates a step); everything else is as by default
    scene_cfg = SceneConfig(image_size=(64, 104)) if args.quick else SceneConfig()
    preset = demo_preset(scene_cfg, args.quick)
    t0 = time.perf_counter()
    train_ds = SyntheticDataset("train", args.train_scenes, scene_cfg, seed=args.seed)
    val_ds = SyntheticDataset("val", args.val_scenes, scene_cfg, seed=args.seed)
    train_scenes = [train_ds[i] for i in tqdm(range(len(train_ds)), desc="scenes train", unit="scene")]
    val_scenes = [val_ds[i] for i in tqdm(range(len(val_ds)), desc="scenes val", unit="scene")]
    t_scenes = time.perf_counter() - t0
    gts = ground_truths(val_scenes, scene_cfg)

    blocks = {MODELS[0]: args.fusion_blocks, MODELS[1]: 0}
    # the recipe's augmentation; GT boxes whose centre leaves the grid after it are dropped
    augmentation = replace(VOD_RECIPE.augmentation, gt_range=tuple(preset.pillar_range))
    augmented = {MODELS[0]: args.augmentation == "on", MODELS[1]: args.augmentation == "on"}
    if args.augmentation == "compare":
        blocks[AUGMENTED_MODEL] = args.fusion_blocks
        augmented[AUGMENTED_MODEL] = True
    models, timings, histories, results, preds_by_model, lighting = {}, {}, {}, {}, {}, {}
    ckpt = torch.load(args.load_checkpoint, map_location="cpu", weights_only=True) if args.load_checkpoint else None

    # The image branch: pre-trained on the train scenes' 2D semantics, frozen, features cached (default);
    # or trained end to end with the detector from scratch (--image-branch end-to-end).
    image_pretrain, branch, readout = None, None, None
    fusion_collate_train = fusion_collate_val = None
    if args.image_branch == "pretrained":
        torch.manual_seed(args.seed)
        branch = ImageBranch(preset.image_depth, preset.image_base_channels, preset.fpn_channels,
                             preset.num_image_levels)
        t0 = time.perf_counter()
        if ckpt is not None:
            branch.load_state_dict(ckpt["image_branch"])
            readout = SemanticReadout(branch.out_channels, len(CLASS_NAMES))
            readout.load_state_dict(ckpt["image_readout"])
            image_pretrain = {"loaded": str(args.load_checkpoint)}
        else:
            log = pretrain_image_branch(branch, train_scenes, args.image_pretrain_steps,
                                        batch_size=min(8, len(train_scenes)),
                                        lr=args.image_pretrain_lr, seed=args.seed, num_classes=len(CLASS_NAMES),
                                        progress=lambda it: tqdm(it, desc="pretrain image branch", unit="step",
                                                                 dynamic_ncols=True))
            readout = log["readout"]
            image_pretrain = {"steps": args.image_pretrain_steps, "seconds": log["seconds"],
                              "final_loss": sum(log["history"][-10:]) / len(log["history"][-10:])}
        seg_val = segmentation_metrics(branch, readout, val_scenes, len(CLASS_NAMES))
        image_pretrain["val_pixel"] = {"classes": ["background", *CLASS_NAMES], **seg_val}
        print("image branch, val pixels (background, " + ", ".join(CLASS_NAMES) + "): IoU "
              + " ".join(f"{v:.2f}" for v in seg_val["iou"]) + ", recall "
              + " ".join(f"{v:.2f}" for v in seg_val["recall"]))
        for p in branch.parameters():
            p.requires_grad_(False)
        bar = dict(unit="batch", dynamic_ncols=True)
        feats_train = precompute_features(branch, train_scenes, progress=lambda it: tqdm(it, desc="image features train", **bar))
        feats_val = precompute_features(branch, val_scenes, progress=lambda it: tqdm(it, desc="image features val", **bar))
        image_pretrain["total_seconds"] = time.perf_counter() - t0
        fusion_collate_train = scene_collate(train_scenes, feats_train)
        fusion_collate_val = scene_collate(val_scenes, feats_val)
    image_source = "precomputed" if branch is not None else "backbone"

    for name, n in blocks.items():
        torch.manual_seed(args.seed)  # same initialisation stream for both models
        model = build_detector(args.detector, preset, num_fusion_blocks=n, fusion=args.fusion,
                               image_features=image_source if n else "backbone").to(args.device)
        val_collate = fusion_collate_val if n else None
        if ckpt is not None:
            if name not in ckpt["models"]:
                raise SystemExit(f"--load-checkpoint {args.load_checkpoint}: no weights for {name!r} "
                                 f"(it holds {sorted(ckpt['models'])}); rerun with the --augmentation it was saved with")
            model.load_state_dict(ckpt["models"][name])
            timings[name] = {"train_seconds": 0.0, "loaded": str(args.load_checkpoint)}
        else:
            log = train(model, train_scenes, args.steps, args.batch_size, args.lr, args.seed, name,
                        collate=fusion_collate_train if n else None,
                        augmentation=augmentation if augmented[name] else None, amp_dtype=args.amp_dtype)
            timings[name] = {"train_seconds": log["seconds"], "seconds_per_step": log["seconds_per_step"]}
            histories[name] = log["history"]
        t0 = time.perf_counter()
        preds_by_model[name] = predict(model, val_scenes, args.batch_size, name, collate=val_collate)
        results[name] = evaluate(preds_by_model[name], gts, CLASS_NAMES)
        if args.lighting:
            lighting[name] = lighting_report(preds_by_model[name], gts, val_scenes)
        timings[name]["eval_seconds"] = time.perf_counter() - t0
        timings[name]["parameters"] = sum(p.numel() for p in model.parameters())
        models[name] = model
    config = {k: (str(v) if isinstance(v, (Path, torch.device, torch.dtype)) else v) for k, v in vars(args).items()}
    if args.save_checkpoint:
        args.save_checkpoint.parent.mkdir(parents=True, exist_ok=True)
        state = {"models": {k: m.state_dict() for k, m in models.items()}, "config": config}
        if branch is not None:
            state.update(image_branch=branch.state_dict(), image_readout=readout.state_dict())
        torch.save(state, args.save_checkpoint)

    table = "\n\n".join(format_table(results, metric=m) for m in ("AP3D_R11", "APBEV_R11"))
    print("\n" + table)
    if args.lighting:
        print("\nmAP (AP3D_R11, entire area) per lighting condition:")
        for name, per in lighting.items():
            print(f"  {name}: " + ", ".join(f"{c} ({v['num_scenes']} scenes) {v['entire_area']['mAP']['AP3D_R11']:.2f}"
                                            for c, v in per.items()))

    # figures
    t0 = time.perf_counter()
    fusion_model = models[MODELS[0]]
    k = min(args.figure_scenes, len(val_scenes))
    seg, pooled, scores = semantic_scores(fusion_model, val_scenes, args.batch_size, fusion_collate_val)
    figures = {"bev": "bev_val_scenes.png", "blur_curves": "blur_curves.png"}
    if branch is not None:
        figures["image_semantics"] = "image_semantics.png"
        plot_image_semantics(args.out / figures["image_semantics"], val_scenes[:k], branch, readout)
    plot_bev(args.out / figures["bev"], val_scenes[:k], {m: p[:k] for m, p in preds_by_model.items()},
             seg[:k], 0.15, preset.pillar_range)
    curves = None
    if pooled.n_fore2d > 0:
        curves = blur_curves(scores, pooled)
        plot_semantic_blur_curves(args.out / figures["blur_curves"], MODELS[0], curves)
    else:
        figures.pop("blur_curves")
    if histories:
        figures["losses"] = "train_loss.png"
        plot_losses(args.out / figures["losses"], histories)
    t_figures = time.perf_counter() - t0

    gap = {r: results[MODELS[0]][r]["mAP"]["AP3D_R11"] - results[MODELS[1]][r]["mAP"]["AP3D_R11"]
           for r in results[MODELS[0]]}
    aug_gain = None
    if AUGMENTED_MODEL in results:
        aug_gain = {r: results[AUGMENTED_MODEL][r]["mAP"]["AP3D_R11"] - results[MODELS[0]][r]["mAP"]["AP3D_R11"]
                    for r in results[MODELS[0]]}
    metrics = {
        "results": results,
        "table": table,
        "fusion_minus_radar_mAP_AP3D_R11": gap,
        "augmentation": {"mode": args.augmentation, "config": dataclasses.asdict(augmentation),
                         "augmented_models": [m for m in blocks if augmented[m]],
                         "augmented_minus_plain_mAP_AP3D_R11": aug_gain},
        "lighting": lighting or None,
        "image_pretrain": image_pretrain,
        "blur_curves": None if curves is None else {
            "tau": curves.tau.tolist(), "blur_ratio": curves.blur_ratio.tolist(),
            "foreground_recall": curves.foreground_recall.tolist(),
            "counts": pooled.counts()},
        "config": config,
        "preset": {k: v for k, v in vars(preset).items()},
        "models": blocks,
        "timings": {"scenes_seconds": t_scenes, "figures_seconds": t_figures, "models": timings,
                    "total_seconds": time.perf_counter() - t_start},
        "final_train_loss": {m: h[-1] for m, h in histories.items()},
        "environment": {"torch": torch.__version__, "python": platform.python_version(),
                        "threads": torch.get_num_threads()},
        "figures": figures,
    }
    (args.out / "metrics.json").write_text(json.dumps(_finite(metrics), indent=1))
    print("\nfusion - radar-only mAP (AP3D_R11): " + ", ".join(f"{r} {g:+.2f}" for r, g in gap.items()))
    if aug_gain is not None:
        print("fusion with - without augmentation, mAP (AP3D_R11): "
              + ", ".join(f"{r} {g:+.2f}" for r, g in aug_gain.items()))
    print(f"total {metrics['timings']['total_seconds']:.0f} s; wrote {args.out}/metrics.json and "
          f"{', '.join(figures.values())}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
