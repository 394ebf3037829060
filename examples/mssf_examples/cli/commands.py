"""Train and evaluate the MSSF example detectors on a View-of-Delft or TJ4DRadSet download.

After ``pip install -e ".[examples]"`` (or the wheel), as ``mssf`` or ``python -m mssf_examples``; with no
install, from the repository root, ``PYTHONPATH=src:examples python -m mssf_examples``::

    mssf train --dataset vod --data-root /data/view_of_delft \\
        --detector pointpillars --out outputs/vod_pointpillars
    mssf eval --checkpoint outputs/vod_pointpillars/checkpoint.pt \\
        --data-root /data/view_of_delft --split val --out outputs/vod_pointpillars/val

``train`` reads the ``--split`` frames with :class:`~mssf_examples.data.kitti_io.KittiFormatDataset`, trains
with :func:`mssf_examples.training.loop.train_detector` and writes ``<out>/checkpoint.pt`` and
``<out>/config.json``; with ``--val-split`` it then evaluates like ``eval`` into ``<out>/eval_<split>/``.
``eval`` writes ``<out>/predictions/<frame id>.txt`` (KITTI format, score last; an empty file for a frame
without detections) for every frame and, when the split has labels, scores them with the dataset's
official protocol (:func:`mssf_examples.evaluation.metrics.evaluate`: ``protocol="vod"``, the VoD kit's entire
annotated area and driving corridor, R11; ``protocol="tj4d"``, the TJ4DRadSet range bins, R40) on the
label files and the prediction files as written, prints the table and writes ``<out>/metrics.json``. See ``docs/real-data.md`` ("Train and evaluate").

The options and the ``--dataset`` table are in :mod:`mssf_examples.cli.args`, the data loading in
:mod:`mssf_examples.cli.loading`; this module re-exports their public names.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import torch

from mssf_blocks.errors import MSSFError

from ..data.augment import augment_batches, augmentation_from_args
from ..data.kitti_export import kitti_lines, write_kitti_file
from ..data.kitti_io import Frame, KittiFormatDataset, parse_labels
from ..evaluation.metrics import evaluate, format_table
from ..models.detectors import build_detector
from ..models.presets import DetectorPreset, authors_preset, tiny_preset
from ..training import distributed
from ..training.loop import batch_order, load_checkpoint, load_resume_state, predict, save_checkpoint, train_detector
from .args import DATASETS, PROG, RECIPES, DatasetSpec, build_parser  # noqa: F401 - part of this module's interface
from .loading import (  # noqa: F401 - scale_batch, _Collate: part of this module's interface
    _Collate, _CollateWithFrames, _Frames, _jsonable, _loader, _open_dataset, _preset_from_json, _preset_to_json,
    scale_batch)

__all__ = ["DatasetSpec", "DATASETS", "cli_tiny_preset", "build_parser", "main"]


def cli_tiny_preset(base: DetectorPreset, image_size: Tuple[int, int]) -> DetectorPreset:
    """:func:`~mssf_examples.models.presets.tiny_preset` widths over ``base``'s full range (CPU smoke runs).

    Voxels ``(0.4, 0.4, base z)`` and pillars ``(0.32, 0.32)`` m, which divide both datasets' ranges
    (VoD 128 x 128 / 160 x 160 cells, TJ4D 176 x 200 / 216 x 248). Not from the paper.
    """
    return tiny_preset(base, name=f"tiny-{base.name}", point_cloud_range=base.point_cloud_range,
                       pillar_range=base.pillar_range, voxel_size=(0.4, 0.4, base.voxel_size[2]),
                       pillar_size=(0.32, 0.32), image_size=tuple(int(s) for s in image_size))


# --------------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------------
def _train(ap: argparse.ArgumentParser, args) -> int:
    spec = DATASETS[args.dataset]
    sensor = args.sensor if "sensor" in args else spec.default_sensor
    batch_size = getattr(args, "batch_size", 4)
    if args.data_root is None:
        ap.error("--data-root: required for train")
    _check_out(ap, args.out)
    if args.fusion_blocks > 4:
        ap.error(f"--fusion-blocks: expected 0..4 (0..3 for pointpillars), got {args.fusion_blocks}")
    if args.detector == "pointpillars" and args.fusion_blocks > 3:
        ap.error(f"--fusion-blocks: expected 0..3 for pointpillars (three 2D blocks), got {args.fusion_blocks}")
    if args.image_weights is not None and not args.image_weights.is_file():
        ap.error(f"--image-weights: file not found: {args.image_weights}")
    ds = _open_dataset(ap, args.data_root, spec, sensor, args.split)
    if len(ds) == 0:
        ap.error(f"--split {args.split}: no frames in {ds.data_dir}")
    if ds.label_dir is None:
        ap.error(f"--data-root {args.data_root}: training needs labels, found no label_2/ folder near {ds.data_dir}")
    if batch_size > len(ds):
        ap.error(f"--batch-size: expected <= {len(ds)} (frames in split {args.split!r}), got {batch_size}")
    val_ds = _open_dataset(ap, args.data_root, spec, sensor, args.val_split) if args.val_split else None
    per_epoch = len(ds) // batch_size
    steps = args.steps if args.steps is not None else max(1, round(args.epochs * per_epoch))

    first = ds.load(ds.frame_ids[0], with_labels=False)
    h, w = first.image_size
    image_size = (max(1, round(h * args.image_scale)), max(1, round(w * args.image_scale)))
    base = {"paper": spec.preset, "authors": authors_preset(spec.preset)}.get(args.preset) or \
        cli_tiny_preset(spec.preset, image_size)
    preset = dataclasses.replace(base, image_size=image_size,
                                 freeze_image_branch=base.freeze_image_branch and not args.train_image_branch)
    torch.manual_seed(args.seed)  # the same initial weights in every process
    model = build_detector(args.detector, preset, num_fusion_blocks=args.fusion_blocks, fusion=args.fusion,
                           score_threshold=args.score_threshold)
    if model.image_branch is not None and model.image_branch.frozen and args.image_weights is None:
        # a frozen branch that loads nothing trains the detector on random image features, without a word
        ap.error("--image-weights: a frozen image branch needs pre-trained weights (the paper: HTC's ResNet-50 + "
                 f"FPN; --preset {args.preset} freezes it); got none. Pass --image-weights FILE (a state_dict of "
                 "mssf_examples.models.image_branch.ImageBranch), or --train-image-branch to train it")
    if args.image_weights is not None and model.image_branch is not None:
        model.image_branch.load_state_dict(torch.load(args.image_weights, map_location="cpu", weights_only=True))

    recipe = RECIPES[args.dataset]
    if recipe.feature_names != tuple(spec.point_format.features):
        ap.error(f"--dataset {args.dataset}: the recipe names point columns {recipe.feature_names}, the point "
                 f"format has {spec.point_format.features}")
    gt_range = preset.pillar_range if args.detector == "pointpillars" else preset.point_cloud_range
    try:
        augmentation = augmentation_from_args(args, recipe.augmentation, gt_range)
    except MSSFError as exc:
        ap.error(f"augmentation options: {exc}")
    if args.lr is None:
        args.lr = recipe.peak_lr(args.fusion_blocks)
    config = dict(
        command="train", dataset=args.dataset, data_root=str(args.data_root), sensor=sensor, split=args.split,
        detector=args.detector, fusion_blocks=args.fusion_blocks, fusion=args.fusion, preset_name=args.preset,
        image_scale=args.image_scale, train_image_branch=args.train_image_branch,
        image_weights=None if args.image_weights is None else str(args.image_weights), steps=steps,
        epochs=steps * batch_size / len(ds), batch_size=batch_size, lr=args.lr, seed=args.seed,
        score_threshold=args.score_threshold, num_frames=len(ds), preset=_preset_to_json(preset),
        augmentation=dataclasses.asdict(augmentation), recipe=recipe.name,
    )
    run = _runtime(ap, args, batch_size)
    resume = _resume_state(ap, args.resume, _jsonable(config)) if args.resume is not None else None
    if resume is not None:
        model.load_state_dict(resume["model"])
    config.update(run.config)
    dist, device = run.dist, run.device
    if dist.is_main:
        args.out.mkdir(parents=True, exist_ok=True)
    start = resume["step"] if resume is not None else 0
    # every process reads its share of the same global batches (one global batch per optimiser step)
    order = distributed.shard_batches(batch_order(len(ds), batch_size, steps, args.seed)[start:], dist.rank,
                                      dist.world_size, args.accumulate)
    collate = _Collate(args.image_scale, preset.pillar_range if args.detector == "pointpillars"
                       else preset.point_cloud_range)
    if dist.is_main:
        print(f"train {args.detector} (n={args.fusion_blocks}, {args.fusion}, preset {preset.name}) on {len(ds)} "
              f"frames of {ds!r}: {steps} steps of {batch_size} ({run.describe()})"
              + (f", resumed at step {start}" if resume else ""), file=sys.stderr)
    distributed.init_distributed(dist, device)
    model = distributed.wrap_model(model, device, dist, args.sync_bn)

    # The augmentation draws: every process its own stream (rank 0's is a single process's), drawn in this
    # process after the loader, so the seed alone fixes them. Their states, torch's CPU generator and, in a
    # run on CUDA, the CUDA generators (any random op in the model) go into every checkpoint and a resumed
    # run restores them: the same draws as an uninterrupted run. (The data order is a function of the
    # seed: batch_order, sliced at start.)
    aug_rng = None if augmentation.is_identity else torch.Generator().manual_seed(args.seed + 1_000_003 * dist.rank)
    if start:
        saved = resume["train_state"].get("rng_states") or []
        if len(saved) == dist.world_size:
            torch.set_rng_state(saved[dist.rank]["torch"])
            if aug_rng is not None and saved[dist.rank].get("augment") is not None:
                aug_rng.set_state(saved[dist.rank]["augment"])
            _restore_cuda_rng(saved[dist.rank].get("cuda"), dist.is_main)
        elif aug_rng is not None:  # a checkpoint without them (older, or another number of processes)
            aug_rng.manual_seed(args.seed + 1_000_003 * dist.rank + 7_919 * start)
            if dist.is_main:
                print(f"--resume: the checkpoint holds {len(saved)} random states for {dist.world_size} "
                      "process(es): augmentations are drawn afresh from here", file=sys.stderr)

    def checkpoint(step: int, state: Dict) -> None:
        mine = {"torch": torch.get_rng_state(), "augment": None if aug_rng is None else aug_rng.get_state(),
                "cuda": _cuda_rng()}
        states = [mine]
        if dist.enabled:  # (every process calls this at the same step)
            states = [None] * dist.world_size
            torch.distributed.all_gather_object(states, mine)
        if dist.is_main:
            save_checkpoint(args.out / "checkpoints" / f"step_{step:06d}.pt", model, _jsonable(config),
                            dict(state, rng_states=states), step)

    batches = _loader(_Frames(ds, True), order, args.workers, collate, device)
    if aug_rng is not None:
        batches = augment_batches(batches, recipe.feature_kinds, augmentation, args.seed, generator=aug_rng)
    log = train_detector(model, batches, steps, args.lr,
                         desc=f"train {args.detector}", progress=not args.no_progress and dist.is_main,
                         device=device, amp_dtype=run.amp_dtype, accumulate=args.accumulate, start_step=start,
                         state=None if resume is None else resume["train_state"], checkpoint=checkpoint,
                         checkpoint_every=args.checkpoint_every)
    if not dist.is_main:  # rank 0 alone writes and evaluates
        return 0
    model = distributed.unwrap_model(model)
    config["train_seconds"] = log["seconds"]
    config["final_loss"] = log["history"][-1]
    ckpt = save_checkpoint(args.out / "checkpoint.pt", model, _jsonable(config))
    (args.out / "config.json").write_text(json.dumps(_jsonable(config), indent=1))
    (args.out / "train_log.json").write_text(json.dumps(_jsonable(log["history"])))
    print(f"wrote {ckpt} and {args.out / 'config.json'} ({log['seconds']:.1f} s, final loss "
          f"{log['history'][-1]['loss']:.4f})", file=sys.stderr)
    if val_ds is not None:
        _evaluate(model, config, val_ds, args.out / f"eval_{args.val_split}", batch_size, args.workers, ckpt,
                  progress=not args.no_progress)
    return 0


def _cuda_rng() -> Optional[List[torch.Tensor]]:
    """The CUDA generators' states where this process uses CUDA (initialised: a CPU run on a GPU machine
    stays off the GPU), else ``None``. Host-side states: no synchronisation, no context on other GPUs."""
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        return torch.cuda.get_rng_state_all()
    return None


def _restore_cuda_rng(states: Optional[List[torch.Tensor]], main: bool) -> None:
    """Put the checkpoint's CUDA generator states back (one per visible GPU); a checkpoint of a CPU run
    holds none, and another GPU count (or no CUDA now) keeps the fresh ones, with a note."""
    if states is None:
        return
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if count == len(states):
        torch.cuda.set_rng_state_all(states)
    elif main:
        print(f"--resume: the checkpoint holds CUDA random states for {len(states)} GPU(s), this process sees "
              f"{count}: random ops on the GPU (if the model has any) draw afresh from here", file=sys.stderr)


def _runtime(ap: argparse.ArgumentParser, args, batch_size: int) -> "distributed.Runtime":
    try:
        return distributed.Runtime.from_args(args, batch_size)
    except MSSFError as exc:
        ap.error(str(exc))


def _resume_state(ap: argparse.ArgumentParser, path: Path, config: Dict) -> Dict:
    try:  # the options that must match: training.RESUME_KEYS (device, processes, --accumulate may differ)
        return load_resume_state(path, expect_config=config)
    except (FileNotFoundError, MSSFError) as exc:
        ap.error(f"--resume: {exc}")


def _evaluate(model, config: Dict, ds: KittiFormatDataset, out: Path, batch_size: int, workers: int,
              checkpoint: Path, progress: bool = True) -> Dict:
    """Predict ``ds``, write prediction files and (with labels) metrics; returns the metrics dict."""
    spec = DATASETS[config["dataset"]]
    with_labels = ds.label_dir is not None and all(ds.paths(i).label.is_file() for i in ds.frame_ids)
    pred_dir = out / "predictions"
    pred_dir.mkdir(parents=True, exist_ok=True)
    chunks = [list(range(i, min(i + batch_size, len(ds)))) for i in range(0, len(ds), batch_size)]
    loader = _loader(_Frames(ds, with_labels), chunks, workers, _CollateWithFrames(config.get("image_scale", 1.0)))
    t0 = time.perf_counter()
    preds: List[Dict] = []
    written: List = []  # the prediction files as the official kit reads them
    gts: List = []
    frames_seen: List[Frame] = []  # without their images and points: a split's images do not fit in memory

    def batches():
        for batch, frames in loader:
            frames_seen.extend(dataclasses.replace(f, image=None, points=f.points[:0], raw_points=f.raw_points[:0])
                               for f in frames)
            yield batch

    for p in predict(model, batches(), total=len(chunks), desc="eval", progress=progress):
        preds.append(p)
    num_det = 0
    for frame, p in zip(frames_seen, preds):
        lines = kitti_lines(p["boxes"], p["labels"], spec.class_names, frame.calib, frame.image_size,
                            scores=p["scores"].double())
        num_det += len(lines)
        write_kitti_file(pred_dir / f"{frame.frame_id}.txt", lines)
        if with_labels:
            written.append(parse_labels("\n".join(lines), source=str(pred_dir / f"{frame.frame_id}.txt")))
            gts.append(frame.objects)  # every label line, as the kit reads label_2
    seconds = time.perf_counter() - t0
    print(f"wrote {len(frames_seen)} prediction files ({num_det} detections) to {pred_dir}", file=sys.stderr)
    metrics: Dict = dict(split=ds.split, num_frames=len(frames_seen), num_detections=num_det,
                         predictions=str(pred_dir), checkpoint=str(checkpoint), predict_seconds=seconds,
                         config=config, environment=dict(torch=torch.__version__, python=platform.python_version(),
                                                         threads=torch.get_num_threads()))
    if with_labels:
        results = evaluate(written, gts, spec.class_names, iou_thresholds=spec.iou_thresholds, protocol=spec.protocol)
        name = f"{config['detector']} n={config['fusion_blocks']}"
        table = "\n\n".join(format_table({name: results}, metric=m) for m in spec.table_metrics)
        print("\n" + table)
        wanted = {c.lower() for c in spec.class_names}
        metrics.update(results=results, table=table, protocol=spec.protocol,
                       num_gt=sum(sum(n.lower() in wanted for n in g.names) for g in gts))
        (out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=1))
        print(f"\nwrote {out / 'metrics.json'}", file=sys.stderr)
    else:
        print(f"split {ds.split!r} has no labels: wrote predictions only", file=sys.stderr)
    return metrics


def _eval(ap: argparse.ArgumentParser, args) -> int:
    try:
        state, config = load_checkpoint(args.checkpoint)
    except (FileNotFoundError, MSSFError) as exc:
        ap.error(f"--checkpoint: {exc}")
    spec = DATASETS.get(config.get("dataset"))
    if spec is None:
        ap.error(f"--checkpoint {args.checkpoint}: unknown dataset {config.get('dataset')!r} in its config")
    if args.data_root is None and config.get("data_root") is None:
        ap.error(f"--data-root: required (the checkpoint {args.checkpoint} names no data root)")
    root = args.data_root if args.data_root is not None else Path(config["data_root"])
    sensor = args.sensor if "sensor" in args else config.get("sensor", spec.default_sensor)
    batch_size = getattr(args, "batch_size", config.get("batch_size", 4))
    ds = _open_dataset(ap, root, spec, sensor, args.split)
    preset = _preset_from_json(config["preset"])
    thr = args.score_threshold if args.score_threshold is not None else config.get("score_threshold", 0.1)
    # a converted authors' checkpoint (convert-authors) carries layout="authors" and their NMS settings
    decode = {k: config[k] for k in ("nms_iou", "max_detections") if k in config}
    model = build_detector(config["detector"], preset, num_fusion_blocks=config["fusion_blocks"],
                           fusion=config["fusion"], score_threshold=thr, layout=config.get("layout", "paper"), **decode)
    model.load_state_dict(state)  # the checkpoint's tensors are on the CPU, whatever device wrote them
    try:
        if distributed.distributed_from_env().enabled:
            raise MSSFError("eval runs in one process; start it without torchrun")
        model.to(distributed.resolve_device(args.device))
    except MSSFError as exc:
        ap.error(str(exc))
    config = dict(config, score_threshold=thr)
    out = args.out if args.out is not None else args.checkpoint.parent / f"eval_{args.split}"
    _check_out(ap, out)
    _evaluate(model, config, ds, out, batch_size, args.workers, args.checkpoint, progress=not args.no_progress)
    return 0


def _one_line(exc: BaseException) -> str:
    """The message of ``exc`` on one line (a ``DataLoader`` worker's re-raised error carries the worker's
    traceback in its message: its last line is the error)."""
    text = str(exc) or type(exc).__name__
    if "Traceback" in text:
        text = [line for line in text.splitlines() if line.strip()][-1]
        head, sep, tail = text.partition(": ")
        text = tail if sep and "Error" in head else text
    if isinstance(exc, OSError) and not isinstance(exc, FileNotFoundError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or text}"
    return " ".join(text.split())


def _check_out(ap: argparse.ArgumentParser, out: Optional[Path]) -> None:
    if out is not None and out.exists() and not out.is_dir():
        ap.error(f"--out: expected a folder (new or existing), got {out}, an existing file")


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point of ``python -m mssf_examples``; returns the exit code (argparse errors exit with 2)."""
    ap = build_parser()
    args = ap.parse_args(None if argv is None else list(argv))
    if args.command == "convert-authors":
        from .convert import run

        return run(args.parser, args)
    from ..models.spconv_helpers import enable_cpu_backward

    enable_cpu_backward()  # spconv 2.3 cannot run backward on CPU-only torch without it
    saved_threads = torch.get_num_threads()  # restored, so that calling main() (tests) leaks nothing
    torch.set_num_threads(args.threads)
    ok = False
    try:
        # errors name the sub-command (its own parser prints the usage)
        try:
            code = _train(args.parser, args) if args.command == "train" else _eval(args.parser, args)
        except (MSSFError, OSError) as exc:
            # bad data found while reading it (a truncated .bin, an unknown class, a calib without P2, a
            # folder that cannot be written): one line and exit status 2, as for a bad option
            distributed.report_failure(exc)
            args.parser.exit(2, f"{args.parser.prog}: error: {_one_line(exc)}\n")
        ok = True
        return code
    except Exception as exc:
        distributed.report_failure(exc)  # under torchrun: which rank failed, before torchrun stops the others
        raise
    finally:
        distributed.shutdown(success=ok)
        torch.set_num_threads(saved_threads)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
