"""Data loading of the training / eval CLI (``python -m mssf_examples``): the dataset, the ``DataLoader``,
the collate functions (ground truth kept on the grid, image scaling with ``lidar2img`` to match), and
the preset / configuration JSON helpers.

Split from :mod:`mssf_examples.cli.commands` (one concept per file); the CLI re-exports these names.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import torch
import torch.nn.functional as F

from mssf_blocks import apply_image_augmentation, image_augmentation_matrix
from mssf_blocks.errors import MSSFError

from ..data.kitti_io import Frame, KittiFormatDataset, frames_to_batch
from ..models.presets import DetectorPreset

__all__ = ["scale_batch"]


def _open_dataset(ap: argparse.ArgumentParser, root: Path, spec, sensor: Optional[str],
                  split: str) -> KittiFormatDataset:
    """The ``split`` frames under ``root`` for ``spec`` (a :class:`~mssf_examples.cli.commands.DatasetSpec`);
    errors become ``ap.error`` messages naming ``--data-root``."""
    if not root.is_dir():
        ap.error(f"--data-root: expected an existing dataset folder, got {root} (not found)")
    try:
        ds = KittiFormatDataset(root, spec.point_format, sensor=sensor, split=None if split == "all" else split,
                                class_names=spec.class_names)
    except (FileNotFoundError, MSSFError) as exc:
        ap.error(f"--data-root {root} (sensor {sensor!r}, split {split!r}): {exc}{_other_layout(root, spec)}")
    _check_point_files(ap, ds, spec)
    return ds


def _other_layout(root: Path, spec) -> str:
    """A hint when ``root`` has the layout of another ``--dataset`` (VoD: ``root/<sensor>/training``,
    TJ4D: ``root/training``)."""
    from .args import DATASETS

    for name, other in DATASETS.items():
        if other is spec:
            continue
        base = root / other.default_sensor if other.default_sensor else root
        if (base / "training" / "velodyne").is_dir() or (base / "velodyne").is_dir():
            return f"; the folder has the layout of --dataset {name}"
    return ""


def _check_point_files(ap: argparse.ArgumentParser, ds: KittiFormatDataset, spec, sample: int = 3) -> None:
    """The first ``sample`` point files hold ``spec``'s columns: decided from their values, not their size
    alone (a size that divides into rows of 7 and of 8 floats fits VoD and TJ4DRadSet alike; VoD frame
    01047 has one): each file is read as every ``--dataset``'s layout and its columns tested
    (:mod:`mssf_examples.data.point_layout`). Refused, naming the file, every reading and ``--dataset``: a file
    that reads as another dataset only, as none, or as two with different meanings."""
    from .args import DATASETS
    from ..data.point_layout import plausible_layouts, read_layouts

    names = {id(other.point_format): name for name, other in DATASETS.items()}
    formats = [other.point_format for other in DATASETS.values()]
    if spec.point_format not in formats:
        formats.insert(0, spec.point_format)
    chosen = names.get(id(spec.point_format), spec.point_format.name)
    for fid in ds.frame_ids[:sample]:
        path = ds.paths(fid).points
        if not path.is_file():
            return  # the loader names a missing file
        nbytes = path.stat().st_size
        if nbytes % 4:
            ap.error(f"{path}: truncated or not a float32 point file ({nbytes} bytes, not a multiple of 4)")
        readings = read_layouts(path, formats)
        mine = next(r for r in readings if r.point_format is spec.point_format)
        good = plausible_layouts(readings)
        said = "; as ".join(r.describe() for r in readings)
        if (len(good) == 1 and good[0] is mine) or (mine.plausible and mine.values == 0):
            continue
        if not any(r.fits for r in readings):
            ap.error(f"{path}: truncated or unreadable point file: {mine.values} float32 values, not rows of "
                     f"{' nor '.join(str(r.point_format.num_channels) for r in readings)} (--dataset {chosen}: "
                     f"{spec.point_format.channels})")
        if len(good) > 1:
            ap.error(f"--dataset {chosen}: {path} reads as more than one dataset's points, as "
                     f"{' and '.join(names.get(id(r.point_format), r.point_format.name) for r in good)} "
                     f"(as {said}): cannot tell which it holds; check the file")
        if len(good) == 1:
            other = names.get(id(good[0].point_format), good[0].point_format.name)
            ap.error(f"--dataset {chosen}: {path} holds {other}'s points, not {chosen}'s (as {said}): a "
                     f"--dataset {other} tree? pass --dataset {other}")
        ap.error(f"--dataset {chosen}: {path} reads as no dataset's points (as {said}): damaged, or not a "
                 f"--dataset {' / '.join(DATASETS)} point file")


class _Frames(torch.utils.data.Dataset):
    """Frames of a :class:`KittiFormatDataset` for a ``DataLoader`` (labels optional)."""

    def __init__(self, ds: KittiFormatDataset, with_labels: bool) -> None:
        self.ds, self.with_labels = ds, with_labels

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, i: int) -> Frame:
        return self.ds.load(self.ds.frame_ids[i], with_labels=self.with_labels)


def scale_batch(batch, scale: float):
    """Resize a batch's images by ``scale`` and map ``lidar2img`` to the resized pixels.

    With pixel ``i``'s centre at ``i`` and edges kept aligned, ``u' = (u + 0.5) s_x - 0.5`` where
    ``s_x = W' / W`` (the same for ``v``), i.e. ``lidar2img' = S @ lidar2img`` with
    ``S = [[s_x, 0, (s_x - 1) / 2], [0, s_y, (s_y - 1) / 2], [0, 0, 1]]``.
    """
    if scale == 1.0:
        return batch
    b, v, c, h, w = batch.images.shape
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    images = F.interpolate(batch.images.flatten(0, 1), size=(nh, nw), mode="bilinear", align_corners=False,
                           antialias=nh < h).unflatten(0, (b, v))
    s, _ = image_augmentation_matrix((h, w), resize=(nh, nw))
    lidar2img = apply_image_augmentation(batch.lidar2img, s)
    return dataclasses.replace(batch, images=images, lidar2img=lidar2img, image_size=None)


def _loader(frames: _Frames, batches: Sequence[Sequence[int]], workers: int, collate, device=None):
    # pinned host memory when the batches go to a GPU: the copies then overlap the computation
    pin = device is not None and torch.device(device).type == "cuda"
    # its own generator: the loader's seed draw leaves torch's global one alone (a resumed run restores
    # that from the checkpoint, and the draw would shift it by one)
    return torch.utils.data.DataLoader(frames, batch_sampler=batches, num_workers=workers, collate_fn=collate,
                                       pin_memory=pin, generator=torch.Generator().manual_seed(0))



class _Collate:
    """Picklable ``collate_fn``: frames -> batch (images scaled by ``scale``).

    With ``gt_range = (x0, y0, z0, x1, y1, z1)`` the ground truth keeps boxes whose centre has
    ``x0 <= x < x1`` and ``y0 <= y < y1`` (as OpenPCDet does before training: boxes the BEV grid cannot
    hold would give the heads targets outside their maps).
    """

    def __init__(self, scale: float, gt_range: Optional[Sequence[float]] = None) -> None:
        self.scale, self.gt_range = scale, None if gt_range is None else tuple(float(v) for v in gt_range)

    def __call__(self, frames: List[Frame]):
        batch = frames_to_batch(frames)
        if self.gt_range is not None:
            x0, y0, _, x1, y1, _ = self.gt_range
            keep = [(g[:, 0] >= x0) & (g[:, 0] < x1) & (g[:, 1] >= y0) & (g[:, 1] < y1) for g in batch.gt_boxes]
            batch = dataclasses.replace(batch, gt_boxes=[g[k] for g, k in zip(batch.gt_boxes, keep)],
                                        gt_labels=[g[k] for g, k in zip(batch.gt_labels, keep)])
        return scale_batch(batch, self.scale)


class _CollateWithFrames(_Collate):
    def __call__(self, frames: List[Frame]):
        return super().__call__(frames), frames


# --------------------------------------------------------------------------------------------------
# Config <-> preset
# --------------------------------------------------------------------------------------------------
def _tuples(x):
    return tuple(_tuples(v) for v in x) if isinstance(x, (list, tuple)) else x


def _preset_to_json(p: DetectorPreset) -> Dict:
    return {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}


def _preset_from_json(d: Dict) -> DetectorPreset:
    return DetectorPreset(**{k: _tuples(v) for k, v in d.items()})


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, Path):
        return str(x)
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
