"""Measurement: how much the MSSF authors' test-time decoding switches change detections.

docs/differences.md row 27. Trains the radar-only (``n = 0``) PointPillars and VoxelNeXt example detectors
of the demo (``examples/demo_steps.py``: generated VoD-like scenes, the demo's CPU-sized preset) for
``--steps`` steps each, then decodes the val scenes' head outputs with the authors' settings
(:data:`~mssf_examples.models.heads.authors.AUTHORS_DECODE`; MSSF-PP's ``nms_pre`` 100) twice: with the
examples' decoding and with their switches
(:func:`~mssf_examples.models.heads.authors.authors_decode_options`: ``multi_class`` for the anchor head;
``class_agnostic_nms`` and ``center_range`` for VoxelNeXt, also each alone). Reported per variant: boxes
in all, boxes only in one of the two outputs (compared as exact (label, score, box) rows), and the VoD
protocol's 3D AP (R40, entire area) with its change.

A small model on synthetic scenes: the numbers size the effect, they say nothing about the authors'
VoD results. Usage: ``python examples/measure_authors_decode.py [--steps 2000] [--train-scenes 400]
[--val-scenes 80] [--detectors pointpillars voxelnext] [--json out.json]``: the defaults (the demo's sizes,
about 12 min on one CPU thread) give the numbers of docs/differences.md row 27.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from demo_steps import demo_preset, ground_truths, predict, scene_collate, train  # noqa: E402
from mssf_examples.models.detectors import build_detector  # noqa: E402
from mssf_examples.evaluation.metrics import evaluate  # noqa: E402
from mssf_examples.models.heads.authors import AUTHORS_DECODE, authors_decode_options  # noqa: E402
from mssf_examples.scenes.synthetic import CLASS_NAMES, SceneConfig, SyntheticDataset  # noqa: E402
from mssf_examples.models.spconv_helpers import enable_cpu_backward  # noqa: E402


def _rows(det) -> set:
    return {(int(label), round(float(score), 6), *(round(float(v), 5) for v in box))
            for box, score, label in zip(det["boxes"], det["scores"], det["labels"])}


def _compare(base, other) -> dict:
    a = [_rows(d) for d in base]
    b = [_rows(d) for d in other]
    return {"boxes": sum(len(x) for x in b), "only_default": sum(len(x - y) for x, y in zip(a, b)),
            "only_switched": sum(len(y - x) for x, y in zip(a, b))}


@torch.no_grad()
def _second_class_candidates(model, scenes, batch_size: int, threshold: float) -> dict:
    """Anchor head, before NMS: among the ``nms_pre`` anchors of highest best-class score, how many
    (anchor, class) pairs score above ``threshold`` and how many of them are not the anchor's best class."""
    model.eval()
    collate, pairs, second = scene_collate(scenes), 0, 0
    for i in range(0, len(scenes), batch_size):
        preds = model.extract(collate(list(range(i, min(i + batch_size, len(scenes))))))[0]
        probs = torch.sigmoid(preds["cls"])
        best = probs.max(dim=-1).values
        for b in range(probs.shape[0]):
            top = best[b].topk(min(model.head.nms_pre, best.shape[1])).indices
            above = probs[b, top] > threshold
            pairs += int(above.sum())
            second += int(above.sum()) - int(above.any(dim=1).sum())
    return {"pairs_above_threshold": pairs, "second_class_pairs": second}


def _ap(preds, gts) -> dict:
    res = evaluate(preds, gts, CLASS_NAMES)["entire_area"]
    return {k: round(res[k]["AP3D_R40"], 3) for k in (*CLASS_NAMES, "mAP")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--train-scenes", type=int, default=400)
    ap.add_argument("--val-scenes", type=int, default=80)
    ap.add_argument("--batch-size", type=int, default=4)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--detectors", nargs="+", choices=("pointpillars", "voxelnext"),
                    default=["pointpillars", "voxelnext"])
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    enable_cpu_backward()
    cfg = SceneConfig()
    preset = demo_preset(cfg)
    train_ds = SyntheticDataset("train", args.train_scenes, cfg, seed=args.seed)
    val_ds = SyntheticDataset("val", args.val_scenes, cfg, seed=args.seed)
    train_scenes = [train_ds[i] for i in range(len(train_ds))]
    val_scenes = [val_ds[i] for i in range(len(val_ds))]
    gts = ground_truths(val_scenes, cfg)
    out = {"config": vars(args) | {"json": str(args.json)}, "detectors": {}}
    variants = {
        "pointpillars": ("anchor", {"multi_class": {"multi_class": True}}),
        "voxelnext": ("voxelnext", {"center_range": {"center_range": tuple(preset.point_cloud_range)},
                                    "class_agnostic_nms": {"class_agnostic_nms": True},
                                    "authors (both)": authors_decode_options("voxelnext", preset.point_cloud_range)}),
    }
    for name, (head, switched) in ((k, v) for k, v in variants.items() if k in args.detectors):
        torch.manual_seed(args.seed)
        thr, nms, top = AUTHORS_DECODE[head]
        model = build_detector(name, preset, num_fusion_blocks=0, score_threshold=thr, nms_iou=nms,
                               max_detections=top)
        if head == "anchor":
            model.head.nms_pre = 100  # their test_cfg nms_pre
        train(model, train_scenes, args.steps, args.batch_size, args.lr, args.seed, name)
        base = predict(model, val_scenes, args.batch_size, f"{name} default")
        entry = {"default": {"boxes": sum(len(d["scores"]) for d in base), "AP3D_R40": _ap(base, gts)}}
        if head == "anchor":
            entry["before_nms"] = _second_class_candidates(model, val_scenes, args.batch_size, thr)
        for label, options in switched.items():
            model.decode_options = options
            preds = predict(model, val_scenes, args.batch_size, f"{name} {label}")
            ap_switched = _ap(preds, gts)
            entry[label] = _compare(base, preds) | {
                "AP3D_R40": ap_switched,
                "mAP_change": round(ap_switched["mAP"] - entry["default"]["AP3D_R40"]["mAP"], 3)}
        model.decode_options = {}
        out["detectors"][name] = entry
        print(name, json.dumps(entry, indent=1), flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
