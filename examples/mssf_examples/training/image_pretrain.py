"""Pre-train the example image branch on generated scenes, then freeze it and cache its features.

The paper's image branch is a ResNet-50 + FPN pre-trained on 2D detection and *frozen* while the 3D
detector trains. Nothing can be downloaded here, so the demo stands in for that pre-training with a
short 2D task on the training scenes themselves: per-pixel semantic segmentation (background incl.
clutter / car / pedestrian / cyclist, from :attr:`Scene.instance_map`) with a **linear** (1 x 1 conv)
classifier on every FPN level. A linear read-out keeps the semantics linearly decodable from the
features, which is what MSDFF's per-head value projection (a linear map) needs.

After pre-training the branch is frozen, and because it no longer changes, its features for every
scene are computed once (:func:`precompute_features`) and handed to the detector as
``RadarCameraBatch.image_features`` (``build_detector(..., image_features="precomputed")``): a training
step then costs only the radar and fusion parts.

Only the train split's labels are used; the 3D boxes are not.
"""

from __future__ import annotations

import time
from typing import Callable, Dict, List, Optional, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

from ..models.image_branch import ImageBranch

__all__ = ["semantic_map", "SemanticReadout", "pretrain_image_branch", "segmentation_metrics",
           "precompute_features", "collate_with_features"]


def semantic_map(scene, num_classes: int = 3) -> Tensor:
    """``(H, W)`` int64 per-pixel class of a scene: ``0`` background (and clutter), ``1 + label`` objects."""
    inst = scene.instance_map
    out = torch.zeros_like(inst)
    g = int(scene.gt_labels.numel())
    is_obj = (inst >= 0) & (inst < g)
    out[is_obj] = scene.gt_labels[inst[is_obj]] + 1
    if int(out.max()) > num_classes:
        raise MSSFError(f"scene.gt_labels: expected labels < num_classes={num_classes}, got {int(out.max()) - 1}")
    return out


class SemanticReadout(nn.Module):
    """A linear per-pixel classifier shared by all FPN levels (1 x 1 conv, ``C -> 1 + num_classes``)."""

    def __init__(self, channels: int, num_classes: int = 3) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, num_classes + 1, 1)

    def forward(self, levels: Sequence[Tensor], image_size) -> List[Tensor]:
        """Levels ``(B, C, H_l, W_l)`` -> per-level logits upsampled to ``image_size``, ``(B, K+1, H, W)``."""
        return [F.interpolate(self.conv(f), size=tuple(image_size), mode="bilinear", align_corners=False)
                for f in levels]


def _class_weights(targets: Tensor, num_classes: int) -> Tensor:
    """Inverse square-root frequency weights (objects are a few % of the pixels), normalised to mean 1."""
    counts = torch.bincount(targets.flatten(), minlength=num_classes + 1).double().clamp_min(1.0)
    w = counts.rsqrt()
    return (w / w.mean()).float()


def pretrain_image_branch(
    branch: ImageBranch,
    scenes: Sequence,
    steps: int,
    batch_size: int = 8,
    lr: float = 3e-3,
    seed: int = 0,
    num_classes: int = 3,
    progress: Optional[Callable] = None,
) -> Dict:
    """Train ``branch`` (in place) with a linear semantic read-out on ``scenes``; returns a log dict.

    AdamW with a one-cycle schedule, cross-entropy averaged over the FPN levels, class weights from
    the pixel frequencies of ``scenes``. ``progress`` wraps the step iterator (e.g. ``tqdm``).
    Deterministic for a fixed ``seed`` (data order and read-out initialisation).
    """
    if steps < 1:
        raise MSSFError(f"steps: expected a positive int, got {steps}")
    if not 1 <= batch_size <= len(scenes):
        raise MSSFError(f"batch_size: expected 1..{len(scenes)} (the number of scenes), got {batch_size}")
    if branch.frozen:
        raise MSSFError("branch: expected a trainable ImageBranch (frozen=False), got a frozen one")
    images = torch.stack([s.image for s in scenes])
    targets = torch.stack([semantic_map(s, num_classes) for s in scenes])
    weights = _class_weights(targets, num_classes)
    g = torch.Generator().manual_seed(seed)
    readout = SemanticReadout(branch.out_channels, num_classes)
    with torch.no_grad():
        readout.conv.weight.normal_(0.0, 0.01, generator=g)
        readout.conv.bias.zero_()
    params = list(branch.parameters()) + list(readout.parameters())
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.3)
    order: List[int] = []
    while len(order) < steps * batch_size:
        order += torch.randperm(len(scenes), generator=g).tolist()
    it = range(steps)
    if progress is not None:
        it = progress(it)
    branch.train()
    history = []
    t0 = time.perf_counter()
    size = images.shape[-2:]
    for step in it:
        idx = order[step * batch_size:(step + 1) * batch_size]
        feats = [f[:, 0] for f in branch(images[idx][:, None])]
        logits = readout(feats, size)
        loss = sum(F.cross_entropy(lg, targets[idx], weight=weights) for lg in logits) / len(logits)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        history.append(float(loss.detach()))
        if hasattr(it, "set_postfix"):
            it.set_postfix(loss=f"{history[-1]:.3f}")
    branch.eval()
    return dict(seconds=time.perf_counter() - t0, history=history, readout=readout, class_weights=weights.tolist())


@torch.no_grad()
def segmentation_metrics(branch: ImageBranch, readout: SemanticReadout, scenes: Sequence, num_classes: int = 3,
                         batch_size: int = 16) -> Dict[str, List[float]]:
    """Per-class pixel recall and IoU of the finest level's read-out on ``scenes`` (classes 0 = background)."""
    branch.eval()
    inter = torch.zeros(num_classes + 1, dtype=torch.float64)
    union = torch.zeros_like(inter)
    total = torch.zeros_like(inter)
    for i in range(0, len(scenes), batch_size):
        chunk = scenes[i:i + batch_size]
        images = torch.stack([s.image for s in chunk])[:, None]
        t = torch.stack([semantic_map(s, num_classes) for s in chunk])
        pred = readout([branch(images)[0][:, 0]], images.shape[-2:])[0].argmax(1)
        for k in range(num_classes + 1):
            inter[k] += ((pred == k) & (t == k)).sum()
            union[k] += ((pred == k) | (t == k)).sum()
            total[k] += (t == k).sum()
    return dict(recall=(inter / total.clamp_min(1)).tolist(), iou=(inter / union.clamp_min(1)).tolist())


@torch.no_grad()
def precompute_features(branch: ImageBranch, scenes: Sequence, batch_size: int = 16,
                        progress: Optional[Callable] = None) -> List[List[Tensor]]:
    """Per scene, the frozen branch's levels ``(V=1, C, H_l, W_l)`` (eval mode, no autograd)."""
    branch.eval()
    out: List[List[Tensor]] = []
    it = range(0, len(scenes), batch_size)
    if progress is not None:
        it = progress(it)
    for i in it:
        chunk = scenes[i:i + batch_size]
        levels = branch(torch.stack([s.image for s in chunk])[:, None])
        out += [[f[b].clone() for f in levels] for b in range(len(chunk))]
    return out


def collate_with_features(scenes: Sequence, features: Sequence[Sequence[Tensor]]):
    """Like :meth:`Scene.collate`, with precomputed ``image_features`` and no images."""
    from dataclasses import replace

    if len(scenes) != len(features):
        raise MSSFError(f"features: expected one entry per scene ({len(scenes)}), got {len(features)}")
    batch = type(scenes[0]).collate(scenes)
    levels = [torch.stack([f[level] for f in features]) for level in range(len(features[0]))]
    return replace(batch, images=None, image_features=levels, image_size=scenes[0].image_size)
