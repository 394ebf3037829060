"""The command line of ``python -m mssf_examples``: what ``--dataset`` selects (:class:`DatasetSpec`, the
training recipe) and the ``train`` / ``eval`` argument parser (options checked where they are parsed:
positive ints, numbers in [0, 1], ``--sensor none``).

Split from :mod:`mssf_examples.cli.commands` (one concept per file); the CLI re-exports these names.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, Optional, Tuple

from ..data.augment import add_augmentation_arguments
from ..data.kitti_io import TJ4D_RADAR, VOD_RADAR, PointFormat
from ..evaluation.metrics import TJ4D_IOU_THRESHOLDS, VOD_IOU_THRESHOLDS
from ..models.detectors import DETECTOR_NAMES
from ..models.presets import TJ4D, TJ4D_RECIPE, VOD, VOD_RECIPE, DetectorPreset, TrainingRecipe
from ..training import distributed
from ..training.threads import DEFAULT_THREADS

__all__ = ["PROG", "DatasetSpec", "DATASETS", "RECIPES", "build_parser"]

PROG = "python -m mssf_examples"


@dataclass(frozen=True)
class DatasetSpec:
    """What ``--dataset`` selects."""

    point_format: PointFormat
    preset: DetectorPreset
    default_sensor: Optional[str]
    iou_thresholds: Dict[str, float]
    #: :func:`mssf_examples.evaluation.metrics.evaluate` protocol and the AP its tables report.
    protocol: str = "vod"
    table_metrics: Tuple[str, ...] = ("AP3D_R11", "APBEV_R11")

    @property
    def class_names(self) -> Tuple[str, ...]:
        return self.preset.class_names


#: ``vod``: VoD release layout, radar (5 scans by default, as in the paper), classes Car / Pedestrian /
#: Cyclist. ``tj4d``: KITTI layout (``training/`` under the root), classes Car / Pedestrian / Cyclist / Truck.
DATASETS: Dict[str, DatasetSpec] = {
    "vod": DatasetSpec(VOD_RADAR, VOD, "radar_5frames", VOD_IOU_THRESHOLDS),
    "tj4d": DatasetSpec(TJ4D_RADAR, TJ4D, None, TJ4D_IOU_THRESHOLDS, "tj4d", ("AP3D_R40", "APBEV_R40")),
}

#: The training recipe (augmentation, learning rate) of each ``--dataset`` (docs/training.md).
RECIPES: Dict[str, TrainingRecipe] = {"vod": VOD_RECIPE, "tj4d": TJ4D_RECIPE}


# --------------------------------------------------------------------------------------------------
# Arguments
# --------------------------------------------------------------------------------------------------
def _checked(cast, ok, what: str):
    """An argparse ``type``: ``cast(text)`` that must satisfy ``ok``, else an error saying ``what`` was expected."""

    def parse(text: str):
        try:
            v = cast(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if not ok(v):
            raise argparse.ArgumentTypeError(f"expected {what}, got {v}")
        return v

    return parse


_positive_int = _checked(int, lambda v: v >= 1, "a positive int")
_non_negative_int = _checked(int, lambda v: v >= 0, "an int >= 0")
_positive_float = _checked(float, lambda v: math.isfinite(v) and v > 0, "a positive number")


def _unit_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {v}")
    return v


def _sensor(text: str) -> Optional[str]:
    return None if text.lower() in ("none", "") else text


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data-root", type=Path, help="dataset root (the folder holding radar_5frames/ for VoD, "
                                                  "training/ for TJ4DRadSet)")
    p.add_argument("--sensor", type=_sensor, default=argparse.SUPPRESS,
                   help="sensor sub-folder (VoD: radar, radar_3frames, radar_5frames [default]; 'none' for a "
                        "root holding training/ directly, the TJ4DRadSet default)")
    p.add_argument("--batch-size", type=_positive_int, default=argparse.SUPPRESS, help="frames per batch (default 4)")
    p.add_argument("--threads", type=_positive_int, default=DEFAULT_THREADS,
                   help=f"torch CPU threads (default {DEFAULT_THREADS}: see mssf_examples/training/threads.py)")
    p.add_argument("--workers", type=_non_negative_int, default=0,
                   help="data-loading worker processes (default 0: load in the main process)")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    distributed.add_arguments(p, training=p.prog.endswith(" train"))


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description="Train / evaluate MSSF example detectors on KITTI-format "
                                 "radar + camera datasets (View-of-Delft, TJ4DRadSet).")
    sub = ap.add_subparsers(dest="command", required=True, metavar="{train,eval,convert-authors}")

    t = sub.add_parser("train", help="train a detector, save a checkpoint", description="Train a detector on "
                       "the --split frames and save <out>/checkpoint.pt and <out>/config.json.")
    t.add_argument("--dataset", choices=tuple(DATASETS), required=True)
    _common(t)
    t.add_argument("--split", default="train",
                   help="ImageSets/<split>.txt to train on (default train; 'all' = every point file)")
    t.add_argument("--val-split", default=None, help="also evaluate this split after training (e.g. val)")
    t.add_argument("--detector", choices=DETECTOR_NAMES, default="pointpillars")
    t.add_argument("--fusion-blocks", type=_non_negative_int, default=2,
                   help="n fusion blocks (paper default 2; 0 = radar only)")
    t.add_argument("--fusion", choices=("msdff", "sff"), default="msdff")
    t.add_argument("--preset", choices=("paper", "authors", "tiny"), default="paper",
                   help="paper: the dataset's paper preset; authors: where the authors' config differs (TJ4D "
                        "voxel z 0.15 m); tiny: few channels and coarse voxels for CPU smoke runs")
    t.add_argument("--train-image-branch", action="store_true",
                   help="train the image branch (the paper's is pre-trained and frozen)")
    t.add_argument("--image-weights", type=Path, default=None,
                   help="state_dict of mssf_examples.models.image_branch.ImageBranch to start the image branch from")
    t.add_argument("--image-scale", type=_positive_float, default=1.0,
                   help="resize images by this factor before the image branch (lidar2img is scaled to match)")
    t.add_argument("--epochs", type=_positive_float, default=80.0, help="passes over the split (default 80)")
    t.add_argument("--steps", type=_positive_int, default=None, help="optimiser steps (overrides --epochs)")
    t.add_argument("--lr", type=_positive_float, default=None,
                   help="one-cycle peak learning rate (default: the recipe's, 10 x its initial lr: VoD n=2 5e-3, "
                        "otherwise 1e-2; docs/training.md)")
    t.add_argument("--seed", type=_non_negative_int, default=0, help="initialisation and data-order seed")
    t.add_argument("--score-threshold", type=_unit_float, default=0.1, help="detections kept in eval (default 0.1)")
    t.add_argument("--out", type=Path, required=True, help="output folder")
    add_augmentation_arguments(t)
    t.set_defaults(parser=t)

    e = sub.add_parser("eval", help="write KITTI prediction files and official-protocol metrics",
                       description="Predict every frame of --split, write <out>/predictions/<id>.txt and, with "
                       "labels, print the official-protocol table (VoD kit / TJ4DRadSet) and write "
                       "<out>/metrics.json.")
    e.add_argument("--checkpoint", type=Path, required=True, help="checkpoint.pt written by train")
    _common(e)
    e.add_argument("--split", default="val",
                   help="ImageSets split (val, test, ...; default val; 'all' = every point file)")
    e.add_argument("--score-threshold", type=_unit_float, default=None,
                   help="detections kept (default: the training run's, 0.1)")
    e.add_argument("--out", type=Path, default=None, help="output folder (default: <checkpoint dir>/eval_<split>)")
    e.set_defaults(parser=e)
    from .convert import add_parser

    add_parser(sub)
    return ap
