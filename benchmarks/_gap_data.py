"""The data of ``framework_gap.py``: the demo's generated scenes as a View-of-Delft release tree at the camera's
full resolution, and the demo's pre-trained image branch as an mmdet-style checkpoint.

The demo renders 152 x 240 images of VoD's 1216 x 1936 camera and evaluates with that camera's calibration, so
that the official kit's 40-pixel image-box rule means on the generated frames what it means on VoD's. A tree
read by a framework gets its 2D boxes and its projection from the calibration files, so the tree holds what a
VoD release holds: ``.jpg`` images at 1216 x 1936 (each scene's image upsampled, bilinear) and the full-resolution
camera matrix; the frameworks' pipelines resize the images back to the demo's 152 x 240 (their ``Resize``, with
the projection following the scale, as on real VoD frames).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Dict, List, Sequence

import torch
import torch.nn.functional as F

from mssf_examples.data.kitti_export import write_vod_tree

SENSOR = "radar_5frames"


def full_resolution(scene, scene_cfg):
    """``scene`` seen by VoD's full-resolution camera: the image upsampled to ``full_image_size``, the camera
    matrix of ``full_intrinsics``."""
    fx, fy, cx, cy = scene_cfg.full_intrinsics
    k = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    image = F.interpolate(scene.image[None], size=tuple(scene_cfg.full_image_size), mode="bilinear",
                          align_corners=False)[0].clamp(0, 1)
    return dataclasses.replace(scene, image=image, intrinsics=k)


def write_full_resolution_tree(root: Path, splits: Dict[str, Sequence], scene_cfg, progress=None) -> Dict[str, List[str]]:
    """``root/radar_5frames`` with every scene of ``splits`` at full resolution (one scene in memory at a time);
    returns ``{split: frame ids}``."""
    ids: Dict[str, List[str]] = {}
    next_id = 0
    for split, scenes in splits.items():
        ids[split] = []
        items = range(len(scenes)) if progress is None else progress(range(len(scenes)), split)
        for i in items:
            out = write_vod_tree(root, {split: [full_resolution(scenes[i], scene_cfg)]}, sensor=SENSOR,
                                 first_id=next_id, image_format="jpg")
            ids[split] += out[split]
            next_id += 1
    for split, frame_ids in ids.items():  # write_vod_tree wrote one frame per call: the whole split now
        (root / SENSOR / "ImageSets" / f"{split}.txt").write_text("".join(i + "\n" for i in frame_ids))
    return ids


def save_image_checkpoint(branch, path: Path) -> Path:
    """The demo's image branch as an mmdet checkpoint: its ``backbone.*`` / ``neck.*`` keys are mmdet's ResNet /
    FPN names (what ``--image-checkpoint`` / ``MODEL.IMAGE_BRANCH.CHECKPOINT`` read)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"meta": {"source": "framework_gap.py: the demo's pre-trained image branch"},
                "state_dict": {k: v.detach().clone() for k, v in branch.state_dict().items()}}, path)
    return path
