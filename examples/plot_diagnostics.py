"""Feature-blurring diagnostics on a small hand-built scene (the paper's Fig. 1(a) and Fig. 7, in miniature).

Usage::

    python examples/plot_diagnostics.py [--out docs/img/feature_blurring.png] [--seed 0] [--steps 500]

What it does:

1. builds a toy radar scene by hand: a pinhole camera looking along +x, a few cars and pedestrians
   (3D boxes, 2D boxes = the projected box corners), radar points *on* the objects, radar points *in
   front of / behind* them on the same viewing rays (they project into the 2D boxes: the 3D blurred
   points) and background points elsewhere;
2. gives every point two toy features: an "image" feature (what a good image branch samples there:
   high inside a 2D box - also for blurred points) and a weak, noisy "radar" feature (higher on
   objects);
3. trains a :class:`~mssf_blocks.heads.SemanticGuidedHead` with the focal loss and the
   ``voxel_foreground_labels`` targets on three feature sets: radar only ("No Image"), image only
   ("No Voxel"), and both ("Fused");
4. classifies the points of a held-out scene with :func:`~mssf_blocks.diagnostics.classify_feature_blurring`
   and plots the image-plane classes and both curves of :func:`~mssf_blocks.diagnostics.blur_curves`.

The numbers illustrate the definitions on synthetic data; they are not the paper's results.
"""

from __future__ import annotations

import argparse
import math
import os
from typing import Dict, List, Tuple

import torch

from mssf_blocks.diagnostics import BlurCurves, blur_curves, classify_feature_blurring, plot_blur_curves
from mssf_blocks.functional.heads import voxel_foreground_labels
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.sparse_voxels import SparseVoxels

H, W, FOCAL, CX, CY = 240, 480, 300.0, 240.0, 100.0
#: (dx, dy, dz) of the toy classes
SIZES = {"car": (4.0, 1.8, 1.5), "pedestrian": (0.6, 0.6, 1.7)}


def lidar2img() -> torch.Tensor:
    """(1, 3, 4): u = cx - f y / x, v = cy - f z / x (camera on the radar, looking along +x)."""
    return torch.tensor([[[CX, -FOCAL, 0.0, 0.0], [CY, 0.0, -FOCAL, 0.0], [1.0, 0.0, 0.0, 0.0]]],
                        dtype=torch.float64)


def project(xyz: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """Normalised uv ``(N, 2)`` and validity ``(N,)`` of sensor-frame points."""
    hom = torch.cat([xyz, torch.ones_like(xyz[:, :1])], dim=1)
    cam = hom @ lidar2img()[0].T
    depth = cam[:, 2]
    ok = depth > 1e-5
    pix = cam[:, :2] / torch.where(ok, depth, torch.ones_like(depth))[:, None]
    uv = (pix + 0.5) / torch.tensor([W, H], dtype=xyz.dtype)
    uv = torch.where(ok[:, None], uv, torch.full_like(uv, -1.0))
    valid = ok & (uv >= 0).all(1) & (uv <= 1).all(1)
    return uv, valid


def box_2d(box: List[float]) -> List[float]:
    """Pixel box ``(x1, y1, x2, y2)`` around the projected corners of a 3D box."""
    x, y, z, dx, dy, dz, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    corners = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for sz in (-1, 1):
                lx, ly = sx * dx / 2, sy * dy / 2
                corners.append([x + c * lx - s * ly, y + s * lx + c * ly, z + sz * dz / 2])
    uv, _ = project(torch.tensor(corners, dtype=torch.float64))
    pix = uv * torch.tensor([W, H], dtype=torch.float64) - 0.5
    return [float(pix[:, 0].min()), float(pix[:, 1].min()), float(pix[:, 0].max()), float(pix[:, 1].max())]


def make_scene(seed: int) -> Dict[str, torch.Tensor]:
    """Points, toy features, 3D and 2D boxes of one hand-built frame."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    boxes = []
    for i, kind in enumerate(["car", "car", "pedestrian", "pedestrian", "pedestrian"]):
        dx, dy, dz = SIZES[kind]
        x = 8.0 + 4.0 * i + 3.0 * float(rand(1))
        y = -8.0 + 4.0 * i + float(rand(1))
        boxes.append([x, y, dz / 2 - 1.0, dx, dy, dz, float(rand(1)) * math.pi])
    pts = []
    for box in boxes:
        x, y, z, dx, dy, dz, yaw = box
        c, s = math.cos(yaw), math.sin(yaw)
        n_on = 12 if dx > 2 else 5
        local = (rand(n_on, 3) - 0.5) * 0.9 * torch.tensor([dx, dy, dz], dtype=torch.float64)
        pts.append(torch.stack([x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1],
                                z + local[:, 2]], 1))
        # Points on the viewing rays through the object, in front of it and behind it: they project
        # onto the object in the image without being on it (feature blurring). Pedestrians are thin, so
        # most of their 2D box is seen "through" - more blurred points relative to points on them.
        n_ray = 6 if dx > 2 else 8
        ray_dir = torch.tensor([x, y, z], dtype=torch.float64)
        scale = torch.cat([0.3 + 0.5 * rand(n_ray // 2), 1.3 + 0.8 * rand(n_ray - n_ray // 2)])
        jitter = (rand(n_ray, 3) - 0.5) * torch.tensor([0.0, 0.8 * dy, 0.8 * dz], dtype=torch.float64)
        pts.append(scale[:, None] * ray_dir + jitter * scale[:, None])
    n_bg = 80
    bg = torch.stack([4 + 40 * rand(n_bg), -20 + 40 * rand(n_bg), -1.0 + 2.0 * rand(n_bg)], 1)
    pts.append(bg)
    xyz = torch.cat(pts)
    uv, valid = project(xyz)
    gt3d = torch.tensor(boxes, dtype=torch.float64)
    gt2d = torch.tensor([box_2d(b) for b in boxes], dtype=torch.float64)
    batch = torch.zeros(xyz.shape[0], dtype=torch.long)
    labels, ignore = voxel_foreground_labels(xyz, batch, [gt3d], margin=0.1)
    pix = uv * torch.tensor([W, H], dtype=torch.float64) - 0.5
    in2d = (valid[:, None] & (pix[:, None, 0] >= gt2d[:, 0]) & (pix[:, None, 0] <= gt2d[:, 2])
            & (pix[:, None, 1] >= gt2d[:, 1]) & (pix[:, None, 1] <= gt2d[:, 3])).any(1)
    n = xyz.shape[0]
    image_feat = in2d.double() + 0.3 * torch.randn(n, generator=g, dtype=torch.float64)
    radar_feat = labels + 0.7 * torch.randn(n, generator=g, dtype=torch.float64)
    return {"xyz": xyz, "uv": uv, "valid": valid, "gt3d": gt3d, "gt2d": gt2d, "batch": batch,
            "labels": labels, "ignore": ignore, "image": image_feat, "radar": radar_feat}


def features(scene: Dict[str, torch.Tensor], variant: str) -> torch.Tensor:
    cols = {"No Image": ["radar"], "No Voxel": ["image"], "Fused": ["radar", "image"]}[variant]
    return torch.stack([scene[c] for c in cols], 1).float()


def as_voxels(feats: torch.Tensor) -> SparseVoxels:
    """Each point as its own voxel (the head only needs features; coords are placeholders)."""
    n = feats.shape[0]
    coords = torch.stack([torch.zeros(n, dtype=torch.long), torch.zeros(n, dtype=torch.long),
                          torch.zeros(n, dtype=torch.long), torch.arange(n)], 1).int()
    return SparseVoxels(feats, coords, (1, 1, n), 1, voxel_size=(1.0, 1.0, 1.0), point_range_min=(0.0, 0.0, 0.0))


def train_head(scenes: List[Dict[str, torch.Tensor]], variant: str, steps: int, seed: int) -> SemanticGuidedHead:
    torch.manual_seed(seed)
    feats = torch.cat([features(s, variant) for s in scenes])
    labels = torch.cat([s["labels"] for s in scenes]).float()
    ignore = torch.cat([s["ignore"] for s in scenes])
    head = SemanticGuidedHead(feats.shape[1], hidden=(16, 16))
    opt = torch.optim.Adam(head.parameters(), lr=2e-2)
    vox = as_voxels(feats)
    for _ in range(steps):
        _, _, logits = head(vox, return_logits=True)
        loss = head.loss(logits, labels, ignore)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return head.eval()


def main(out: str = "docs/img/feature_blurring.png", seed: int = 0, steps: int = 500) -> Dict[str, BlurCurves]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    train = [make_scene(seed * 100 + i) for i in range(8)]
    test = make_scene(seed * 100 + 99)
    cls = classify_feature_blurring(test["xyz"], test["batch"], test["uv"], [test["gt3d"]],
                                    boxes_2d=[test["gt2d"]], image_size=(H, W), valid=test["valid"])
    curves = {}
    for variant in ("No Image", "No Voxel", "Fused"):
        head = train_head(train, variant, steps, seed)
        with torch.no_grad():
            _, scores = head(as_voxels(features(test, variant)))
        curves[variant] = blur_curves(scores, cls)

    fig = plt.figure(figsize=(13, 3.8))
    grid = fig.add_gridspec(1, 3, width_ratios=[1.5, 1, 1])
    ax_img = fig.add_subplot(grid[0])
    pix = (test["uv"] * torch.tensor([W, H], dtype=torch.float64) - 0.5).numpy()
    for x1, y1, x2, y2 in test["gt2d"].tolist():
        ax_img.add_patch(Rectangle((x1, y1), x2 - x1, y2 - y1, fill=False, color="tab:blue", lw=1.5))
    groups = [
        (~cls.fore2d & test["valid"], "lightgray", "o", f"other ({int((~cls.fore2d & test['valid']).sum())})"),
        (cls.fore3d, "tab:green", "o", f"3D foreground ({cls.n_fore3d})"),
        (cls.blurred, "tab:red", "x", f"3D blurred ({cls.n_blurred})"),
    ]
    for mask, colour, marker, label in groups:
        ax_img.scatter(pix[mask.numpy(), 0], pix[mask.numpy(), 1], s=22, c=colour, marker=marker, label=label)
    ax_img.set_xlim(0, W)
    ax_img.set_ylim(H, 0)
    ax_img.set_aspect("equal")
    ax_img.set_title(f"projected radar points, 2D GT boxes (n_fore2d = {cls.n_fore2d})")
    ax_img.legend(loc="lower left", fontsize=8)
    plot_blur_curves(curves, axes=[fig.add_subplot(grid[1]), fig.add_subplot(grid[2])])
    fig.suptitle("Feature blurring on a hand-built toy scene (illustration, not paper results)", fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    for name, c in curves.items():
        i = int(torch.argmin((c.tau - 0.5).abs()))
        print(f"{name:9s} tau=0.5: blur ratio {float(c.blur_ratio[i]):.3f}  "
              f"foreground recall {float(c.foreground_recall[i]):.3f}")
    print(f"classes: {cls.counts()}  ->  {out}")
    return curves


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="docs/img/feature_blurring.png")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=500)
    args = parser.parse_args()
    main(args.out, args.seed, args.steps)
