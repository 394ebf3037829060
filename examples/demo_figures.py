"""The figures of ``examples/train_demo.py``: BEV views of val scenes with GT and predicted boxes and the
fusion model's semantic scores per lifted voxel (paper Fig. 5), the image branch's 2D read-out, the
training losses and the blur-ratio / foreground-recall curves (paper Fig. 7). PNG files, matplotlib's
Agg backend.

Split from ``train_demo.py`` (one concept per file); ``train_demo`` re-exports every name.
"""

from __future__ import annotations

from pathlib import Path
from typing import Dict, List

import torch

from mssf_blocks.diagnostics import plot_blur_curves
from mssf_examples.training.image_pretrain import semantic_map
from mssf_examples.scenes.synthetic import CLASS_NAMES

__all__ = ["plot_bev", "plot_image_semantics", "plot_losses", "plot_semantic_blur_curves"]


def _draw_boxes(ax, boxes, colour, lw=1.2, ls="-"):
    if len(boxes) == 0:
        return
    for c in _bev_corners(boxes):
        ax.plot([*c[:, 1], c[0, 1]], [*c[:, 0], c[0, 0]], color=colour, lw=lw, ls=ls)


def _bev_corners(boxes):
    import numpy as np

    b = boxes.double().numpy()
    cos, sin = np.cos(b[:, 6]), np.sin(b[:, 6])
    local = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5]])
    dx = local[None, :, 0] * b[:, None, 3]
    dy = local[None, :, 1] * b[:, None, 4]
    x = b[:, None, 0] + dx * cos[:, None] - dy * sin[:, None]
    y = b[:, None, 1] + dx * sin[:, None] + dy * cos[:, None]
    return np.stack([x, y], -1)


def plot_bev(path: Path, scenes, preds_by_model, seg, score_threshold: float, rng) -> None:
    """One row per scene: radar points + GT + predictions of each model, then the fusion model's scores."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colours = {0: "tab:blue", 1: "tab:red", 2: "tab:green"}
    n = len(scenes)
    names = list(preds_by_model)
    fig, axes = plt.subplots(n, len(names) + 1, figsize=(3.2 * (len(names) + 1), 3.3 * n), squeeze=False)
    x0, y0, _, x1, y1, _ = rng
    for r, s in enumerate(scenes):
        pts = s.points.numpy()
        for c, name in enumerate(names):
            ax = axes[r, c]
            ax.scatter(pts[:, 1], pts[:, 0], s=2, c="0.5")
            for k, col in colours.items():
                _draw_boxes(ax, s.gt_boxes[s.gt_labels == k], col, lw=2.0)
            p = preds_by_model[name][r]
            keep = p["scores"] >= score_threshold
            for k, col in colours.items():
                _draw_boxes(ax, p["boxes"][keep & (p["labels"] == k)], "k", lw=0.9, ls="--")
            ax.set_title(f"{name}\nscene {r} ({s.lighting})", fontsize=8)
        ax = axes[r, -1]
        if seg is not None:
            cen, sc = seg[r]
            im = ax.scatter(cen[:, 1], cen[:, 0], s=6, c=sc, cmap="viridis", vmin=0, vmax=1)
            for k, col in colours.items():
                _draw_boxes(ax, s.gt_boxes[s.gt_labels == k], col, lw=1.5)
            fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title("MSSF semantic score per lifted voxel", fontsize=8)
        for ax in axes[r]:
            ax.set_xlim(y1, y0)  # y to the left, as seen from above looking forward
            ax.set_ylim(x0, x1)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=6)
    fig.suptitle(f"BEV (x up, y left). GT thick: car blue, ped. red, cyc. green; predictions dashed "
                 f"(score >= {score_threshold})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


@torch.no_grad()
def plot_image_semantics(path: Path, scenes, branch, readout) -> None:
    """Per scene: the camera image, the 2D semantic ground truth and the frozen branch's linear read-out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["0.85", "tab:blue", "tab:red", "tab:green"])
    fig, axes = plt.subplots(len(scenes), 3, figsize=(9.6, 2.1 * len(scenes)), squeeze=False)
    for r, s in enumerate(scenes):
        pred = readout([branch(s.image[None, None])[0][:, 0]], s.image_size)[0].argmax(1)[0]
        panels = ((s.image.permute(1, 2, 0).clamp(0, 1).numpy(), f"image ({s.lighting})"),
                  (semantic_map(s, len(CLASS_NAMES)).numpy(), "2D semantics (GT)"),
                  (pred.numpy(), "frozen branch, linear read-out (P2)"))
        for ax, (img, title) in zip(axes[r], panels):
            if img.ndim == 2:
                ax.imshow(img, cmap=cmap, vmin=0, vmax=3, interpolation="nearest")
            else:
                ax.imshow(img)
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.suptitle("Image branch pre-training (grey background/clutter, blue car, red ped., green cyc.)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_losses(path: Path, histories: Dict[str, List[Dict[str, float]]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3))
    for name, h in histories.items():
        ax.plot([r["loss"] for r in h], label=name, lw=0.8)
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_semantic_blur_curves(path: Path, name: str, curves) -> None:
    """The blur ratio / foreground recall of model ``name``'s semantic head (``curves``: a
    :func:`~mssf_blocks.diagnostics.blur_curves` result) on the val voxels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    plt.close(plot_blur_curves({name: curves}, path=str(path),
                               title="Semantic head on val lifted voxels (paper Fig. 7)"))
