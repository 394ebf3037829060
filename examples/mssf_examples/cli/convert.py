"""``python -m mssf_examples convert-authors CHECKPOINT --out FILE``: an authors' checkpoint for the examples.

Reads their mmengine checkpoint (``torch.load`` on the CPU, tensors only), converts it with
:func:`mssf_examples.models.authors_checkpoint.convert_authors` into the example detector built as theirs
(:func:`authors_detector`: ``MSSFDetector(..., layout="authors")`` on :func:`authors_detector_preset`),
checks that every tensor of the detector is filled and that it loads with ``strict=True``, prints the
mapped / ignored / missing report and writes ``--out`` as a checkpoint of ``train`` (``format``,
``model``, ``config``: detector, fusion blocks, ``layout="authors"``, the preset, their decoding settings;
plus ``report``), so that ``python -m mssf_examples eval --checkpoint FILE --data-root DATA`` evaluates it.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from mssf_blocks.errors import MSSFError

from ..models.authors_checkpoint import LAYOUTS, convert_authors, unwrap_checkpoint
from ..training.loop import CHECKPOINT_FORMAT
from .args import PROG
from .loading import _jsonable, _preset_to_json

__all__ = ["add_parser", "authors_detector", "authors_detector_preset", "run"]


def add_parser(sub) -> argparse.ArgumentParser:
    c = sub.add_parser("convert-authors", help="convert an MSSF authors' checkpoint for the example models",
                       description="Convert a checkpoint of the MSSF authors (EricLiuhhh/MSSF) into the example "
                       "detector built as theirs (layout='authors'); print what was mapped, ignored (and why) and missing; "
                       "write a checkpoint that 'eval --checkpoint' evaluates.")
    c.add_argument("checkpoint", type=Path, help="their .pth (mmengine checkpoint or bare state dict)")
    c.add_argument("--out", type=Path, required=True, help="checkpoint file to write (the train command's format, with the report)")
    c.add_argument("--layout", choices=LAYOUTS, default="mssf_pp",
                   help="their model: mssf_pp (PointPillars) or mssf_v (VoxelNeXt); default mssf_pp")
    c.add_argument("--dataset", choices=("vod", "tj4d"), default="vod", help="the preset the model was trained on")
    c.set_defaults(parser=c)
    return c


def authors_detector_preset(dataset: str):
    """The preset of their detectors: the dataset's (:func:`~mssf_examples.models.presets.authors_preset`: TJ4D voxel
    z 0.15 m), their five FPN levels (``num_outs=5``, all fused) and their anchor centres."""
    from ..models.heads.authors import authors_anchor_z_centers
    from ..models.presets import TJ4D, VOD, authors_preset

    p = authors_preset(VOD if dataset == "vod" else TJ4D)
    return dataclasses.replace(p, num_image_levels=5, image_depth=50, fpn_channels=256,
                               anchor_z_centers=authors_anchor_z_centers(p.class_names, p.anchor_sizes, dataset))


def authors_detector(dataset: str, layout: str, theirs):
    """The example detector built as their ``layout`` (``MSSFDetector(..., layout="authors")``) and its
    ``config`` (what ``eval`` rebuilds it from)."""
    from ..models.detectors import build_detector
    from ..models.heads.authors import AUTHORS_DECODE

    preset = authors_detector_preset(dataset)
    if layout == "mssf_v":
        enc = "pts_middle_encoder.fusion_blocks."
        locs = {k[len(enc):].split(".")[0] for k in theirs if k.startswith(enc)}
        sff = any(k.startswith(enc) and ".img_transform." in k for k in theirs)
        detector, blocks, fusion, (thr, nms, top) = "voxelnext", len(locs), "sff" if sff else "msdff", AUTHORS_DECODE["voxelnext"]
    else:
        detector, blocks, fusion, (thr, nms, top) = "pointpillars", 2, "msdff", AUTHORS_DECODE["anchor"]
    model = build_detector(detector, preset, num_fusion_blocks=blocks, fusion=fusion, layout="authors",
                           score_threshold=thr, nms_iou=nms, max_detections=top)
    config = dict(command="convert-authors", dataset=dataset, detector=detector, fusion_blocks=blocks, fusion=fusion,
                  layout="authors", authors_layout=layout, preset_name="authors", preset=_preset_to_json(preset),
                  score_threshold=thr, nms_iou=nms, max_detections=top)
    return model, config, 64 if layout == "mssf_pp" else 32


def run(ap: argparse.ArgumentParser, args) -> int:
    if not args.checkpoint.is_file():
        ap.error(f"checkpoint: no such file {args.checkpoint}")
    ckpt = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
    try:
        model, config, channels = authors_detector(args.dataset, args.layout, unwrap_checkpoint(ckpt))
        sd, report = convert_authors(ckpt, model, args.layout, stage_channels=channels)
    except MSSFError as exc:
        ap.error(str(exc))
    strict = not report.missing
    if strict:
        model.load_state_dict(sd, strict=True)
        config["source"] = str(args.checkpoint)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"format": CHECKPOINT_FORMAT, "model": model.state_dict(), "config": _jsonable(config),
                    "report": _jsonable({"mapped": report.mapped, "ignored": report.ignored, "missing": report.missing})},
                   args.out)
    print(report.summary())
    print(f"loaded with strict=True; wrote {args.out} (evaluate it: {PROG} eval --checkpoint {args.out} "
          f"--data-root DATA --split val)" if strict else f"NOT loadable with strict=True; wrote nothing")
    return 0 if strict else 1
