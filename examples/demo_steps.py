"""The steps of ``examples/train_demo.py`` on generated scenes: the demo's preset, the val split's
ground truth for the official VoD protocol, batches (with or without cached image features), training,
prediction, the fusion model's semantic scores per lifted voxel and AP per lighting condition.

Split from ``train_demo.py`` (one concept per file): the script orchestrates and reports, these build
and run the models; ``train_demo`` re-exports every name.
"""

from __future__ import annotations

from typing import Dict, List

import torch

from mssf_blocks.diagnostics import classify_projection
from mssf_blocks.geometry import VoxelCentroidProjector
from mssf_examples.data.augment import augment_batches
from mssf_examples.evaluation.metrics import evaluate
from mssf_examples.training.image_pretrain import collate_with_features
from mssf_examples.data.kitti_io import Calibration
from mssf_examples.models.presets import VOD, VOD_RECIPE, DetectorPreset, tiny_preset
from mssf_examples.scenes.synthetic import CLASS_NAMES, LIGHTING_CONDITIONS, Scene, SceneConfig
from mssf_examples.training.loop import batch_order, train_detector
from mssf_examples.training.loop import predict as predict_detections

__all__ = ["demo_preset", "ground_truths", "scene_collate", "train", "predict", "semantic_scores",
           "lighting_report"]


def demo_preset(scene_cfg: SceneConfig, quick: bool = False) -> DetectorPreset:
    """A small VoD-like preset over the scenes' range (not from the paper: CPU-sized widths).

    Pillars of 0.32 m (80 x 80 over 25.6 m), a ResNet-18 image branch with 8 base channels and a
    16-channel FPN (pre-trained on the train scenes by default, see ``--image-branch``).
    """
    r = tuple(scene_cfg.point_cloud_range)
    ps = 0.64 if quick else 0.32
    return tiny_preset(
        VOD, name="demo", point_cloud_range=r, pillar_range=r, pillar_size=(ps, ps), voxel_size=(0.2, 0.2, 0.25),
        image_size=tuple(scene_cfg.image_size), image_base_channels=4 if quick else 8, fpn_channels=16,
        pfn_channels=16, pillar_filters=(16, 32, 32), pillar_upsample_filters=(16, 16, 16),
        lift_z_size=0.5, msdff_heads=2, msdff_points=2, seg_hidden=(16,),
    )


def ground_truths(scenes: List[Scene], scene_cfg: SceneConfig) -> List[Dict]:
    """Per val scene the GT dict of the official VoD protocol: sensor boxes plus the calibration of
    VoD's full-resolution camera (the scenes render a scaled-down image of it), so that the kit's 40 px
    image-box rule means what it means on the real 1216-pixel-high images."""
    fx, fy, cx, cy = scene_cfg.full_intrinsics
    p2 = torch.tensor([[fx, 0.0, cx, 0.0], [0.0, fy, cy, 0.0], [0.0, 0.0, 1.0, 0.0]], dtype=torch.float64)
    return [dict(boxes=s.gt_boxes.double(), labels=s.gt_labels, image_size=tuple(scene_cfg.full_image_size),
                 calib=Calibration(P2=p2, R0_rect=torch.eye(3, dtype=torch.float64),
                                   Tr_velo_to_cam=s.sensor_to_camera.to(torch.float64)[:3].clone()))
            for s in scenes]


def scene_collate(scenes: List[Scene], features=None):
    """``collate(indices)`` for ``scenes``: ``Scene.collate``, or with precomputed image features
    (``features[i]`` of ``scenes[i]``) ``collate_with_features``."""
    if features is None:
        return lambda idx: Scene.collate([scenes[i] for i in idx])
    return lambda idx: collate_with_features([scenes[i] for i in idx], [features[i] for i in idx])


def train(model, scenes: List[Scene], steps: int, batch_size: int, lr: float, seed: int, desc: str,
          collate=None, augmentation=None, amp_dtype=None) -> Dict:
    """Train ``model`` in place (on its device) on a seeded data order; ``collate(indices)`` builds a batch
    (default: ``Scene.collate``); ``augmentation`` (an :class:`~mssf_examples.data.augment.AugmentationConfig`)
    augments every sample, drawn from ``seed``; ``amp_dtype`` the autocast dtype (``None``: float32).
    The loop is :func:`mssf_examples.training.loop.train_detector`."""
    collate = collate or scene_collate(scenes)
    order = batch_order(len(scenes), batch_size, steps, seed)
    batches = (collate(idx) for idx in order)
    if augmentation is not None:  # the scenes' 7 columns are VoD's
        batches = augment_batches(batches, VOD_RECIPE.feature_kinds, augmentation, seed)
    return train_detector(model, batches, steps, lr, desc=f"train {desc}", amp_dtype=amp_dtype)


def predict(model, scenes: List[Scene], batch_size: int, desc: str, collate=None) -> List[Dict[str, torch.Tensor]]:
    collate = collate or scene_collate(scenes)
    chunks = [list(range(i, min(i + batch_size, len(scenes)))) for i in range(0, len(scenes), batch_size)]
    return predict_detections(model, (collate(idx) for idx in chunks), total=len(chunks), desc=f"eval {desc}")


@torch.no_grad()
def semantic_scores(model, scenes: List[Scene], batch_size: int, collate=None):
    """Per scene: the fused voxels' centroids and sigmoid scores; pooled blur classification + scores."""
    collate = collate or scene_collate(scenes)
    model.eval()
    projector = VoxelCentroidProjector()
    per_scene, classes, scores = [], [], []
    for i in range(0, len(scenes), batch_size):
        chunk = scenes[i:i + batch_size]
        batch = collate(list(range(i, i + len(chunk))))
        batch = batch.to(next(model.parameters()).device)
        _, out, pts, pb = model.extract(batch)
        v = out.seg_voxels
        proj = projector(v, pts[:, :3], pb, batch.lidar2img, batch.image_size)
        s = torch.sigmoid(out.seg_logits.float())
        classes.append(classify_projection(proj, [c.gt_boxes for c in chunk],
                                           boxes_2d=[c.gt_boxes_2d for c in chunk], image_size=batch.image_size))
        scores.append(s)
        for b in range(len(chunk)):
            m = proj.batch_index == b
            per_scene.append((proj.centroid[m].numpy(), s[m].numpy()))
    from mssf_blocks.diagnostics import BlurClassification

    pooled = BlurClassification.from_masks(torch.cat([c.fore2d for c in classes]),
                                           torch.cat([c.in_box3d for c in classes]))
    return per_scene, pooled, torch.cat(scores)


def lighting_report(preds, gts, scenes) -> Dict[str, Dict]:
    out = {}
    for cond in LIGHTING_CONDITIONS:
        idx = [i for i, s in enumerate(scenes) if s.lighting == cond]
        if idx:
            res = evaluate([preds[i] for i in idx], [gts[i] for i in idx], CLASS_NAMES)
            out[cond] = dict(num_scenes=len(idx), **res)
    return out
