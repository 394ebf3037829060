"""``python -m mssf_examples convert-authors CHECKPOINT --out FILE``: an authors' checkpoint for the examples.

Reads their mmengine checkpoint (``torch.load`` on the CPU, tensors only), converts it with
:func:`mssf_examples.authors_checkpoint.convert_authors` into the matching example model built for the
dataset's preset, checks that it loads with ``strict=True``, writes ``{"layout", "dataset", "state_dict",
"report"}`` to ``--out`` and prints the mapped / ignored / missing report.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from mssf_blocks.errors import MSSFError

from .authors_checkpoint import LAYOUTS, convert_authors, unwrap_checkpoint

__all__ = ["add_parser", "run"]


def add_parser(sub) -> argparse.ArgumentParser:
    c = sub.add_parser("convert-authors", help="convert an MSSF authors' checkpoint for the example models",
                       description="Convert a checkpoint of the MSSF authors (EricLiuhhh/MSSF) into the example "
                       "model of the same layout; print what was mapped, ignored (and why) and missing.")
    c.add_argument("checkpoint", type=Path, help="their .pth (mmengine checkpoint or bare state dict)")
    c.add_argument("--out", type=Path, required=True, help="file to write the converted state dict and report to")
    c.add_argument("--layout", choices=LAYOUTS, default="mssf_pp",
                   help="their model: mssf_pp (PointPillars) or mssf_v (VoxelNeXt); default mssf_pp")
    c.add_argument("--dataset", choices=("vod", "tj4d"), default="vod", help="the preset the model was trained on")
    c.set_defaults(parser=c)
    return c


def _model(dataset: str, layout: str, theirs):
    from .backbones import AuthorsPointPillarsBackbone, VoxelNeXtBackbone
    from .presets import TJ4D, VOD
    from .voxelize import VoxelGrid

    p = VOD if dataset == "vod" else TJ4D
    if layout == "mssf_v":
        enc = "pts_middle_encoder.fusion_blocks."
        locs = {k[len(enc):].split(".")[0] for k in theirs if k.startswith(enc)}
        sff = any(k.startswith(enc) and ".img_transform." in k for k in theirs)
        return VoxelNeXtBackbone(p.num_point_features, VoxelGrid(p.point_cloud_range, p.voxel_size), authors_layout=True,
                                 num_fusion_blocks=len(locs), fusion="sff" if sff else "msdff",
                                 image_channels=[256] * 5), 32
    r = p.pillar_range
    grid = VoxelGrid(r, (p.pillar_size[0], p.pillar_size[1], r[5] - r[2]))
    return AuthorsPointPillarsBackbone(p.num_point_features, grid, [256] * 5), 64


def run(ap: argparse.ArgumentParser, args) -> int:
    if not args.checkpoint.is_file():
        ap.error(f"checkpoint: no such file {args.checkpoint}")
    ckpt = torch.load(args.checkpoint, map_location="cpu", weights_only=True)
    try:
        model, channels = _model(args.dataset, args.layout, unwrap_checkpoint(ckpt))
        sd, report = convert_authors(ckpt, model, args.layout, stage_channels=channels)
    except MSSFError as exc:
        ap.error(str(exc))
    strict = not report.missing
    if strict:
        model.load_state_dict(sd, strict=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"layout": args.layout, "dataset": args.dataset, "state_dict": sd,
                "report": {"mapped": report.mapped, "ignored": report.ignored, "missing": report.missing}}, args.out)
    print(report.summary())
    print(f"{'loaded with strict=True' if strict else 'NOT loadable with strict=True'}; wrote {args.out}")
    return 0 if strict else 1
