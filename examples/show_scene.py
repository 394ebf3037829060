"""Render one synthetic scene to a PNG: camera view with 2D boxes and radar points, plus a BEV panel.

Usage::

    python examples/show_scene.py --seed 3 --out scene.png [--lighting dark] [--scans 5] [--lighting-row]

Left: the image with the GT 2D boxes (class colours) and the radar points projected into it, coloured by
ego-compensated Doppler ``v_rc``; 3D-blurred points (inside a 2D box, outside every 3D box) are drawn
as magenta crosses. Right: bird's-eye view with GT boxes (class colours, arrow = velocity), clutter items
(grey, dashed) and the radar points coloured by ``v_rc``.
"""

from __future__ import annotations

import argparse
import io
import os
import sys
from dataclasses import replace
from typing import Optional, Sequence

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from mssf_examples.scenes.synthetic import CLASS_NAMES, CLUTTER_KINDS, SceneConfig, box_corners, generate_scene  # noqa: E402

_CLASS_COLOURS = ("tab:red", "tab:green", "tab:orange")


def render_scene_png(seed: int, out: str, lighting: Optional[str] = None, num_scans: int = 5, dpi: int = 80,
                     lighting_row: bool = False) -> str:
    """Generate scene ``seed`` and write the figure to ``out``; returns ``out``.

    ``lighting_row`` adds a row with the same scene's image under normal, dark and dazzle lighting.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = SceneConfig(lighting=lighting, num_scans=num_scans)
    s = generate_scene(seed, cfg)
    pts = s.points.numpy().astype(np.float64)
    h, w = s.image_size
    l2i = s.lidar2img.numpy()
    hom = np.concatenate([pts[:, :3], np.ones((len(pts), 1))], 1) @ l2i.T
    front = hom[:, 2] > 0
    uv = hom[:, :2] / np.where(front, hom[:, 2], 1.0)[:, None]
    on_img = front & (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
    blurred = s.blurred_point_mask.numpy()
    vmax = max(2.0, float(np.abs(pts[:, 5]).max()) if len(pts) else 2.0)

    if lighting_row:
        fig = plt.figure(figsize=(11, 6.6))
        grid = fig.add_gridspec(2, 6, height_ratios=[4.2, 2.4])
        ax0, ax1 = fig.add_subplot(grid[0, :4]), fig.add_subplot(grid[0, 4:])
        for j, cond in enumerate(("normal", "dark", "dazzle")):
            ax = fig.add_subplot(grid[1, 2 * j:2 * j + 2])
            ax.imshow(generate_scene(seed, replace(cfg, lighting=cond)).image.permute(1, 2, 0).numpy())
            ax.set_title(f"same scene, {cond}", fontsize=8)
            ax.set_xticks([])
            ax.set_yticks([])
    else:
        fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.2), gridspec_kw=dict(width_ratios=[1.55, 1]))
    ax0.imshow(s.image.permute(1, 2, 0).numpy(), extent=(-0.5, w - 0.5, h - 0.5, -0.5))
    for (l, t, r, b), lab in zip(s.gt_boxes_2d.numpy(), s.gt_labels.tolist()):
        ax0.add_patch(plt.Rectangle((l, t), r - l, b - t, fill=False, lw=1.2, ec=_CLASS_COLOURS[lab]))
    m = on_img & ~blurred
    sc = ax0.scatter(uv[m, 0], uv[m, 1], c=pts[m, 5], cmap="coolwarm", vmin=-vmax, vmax=vmax, s=7,
                     edgecolors="k", linewidths=0.3)
    mb = on_img & blurred
    ax0.scatter(uv[mb, 0], uv[mb, 1], marker="x", c="magenta", s=14, linewidths=1.0, label="3D-blurred")
    ax0.set_xlim(-0.5, w - 0.5)
    ax0.set_ylim(h - 0.5, -0.5)
    ax0.set_title(f"seed {seed}  lighting: {s.lighting}  ({len(pts)} points, {int(blurred.sum())} blurred)", fontsize=9)
    ax0.legend(loc="lower right", fontsize=7)
    ax0.set_xticks([])
    ax0.set_yticks([])

    # BEV: x forward is up, y left is left.
    for box, kind in zip(s.clutter_boxes.numpy(), s.clutter_kinds.tolist()):
        c = box_corners(box)[0, [0, 2, 6, 4, 0]]  # bottom... any 4 corners with the same z bit, in ring order
        ax1.plot(-c[:, 1], c[:, 0], "--", color="0.45", lw=1)
        ax1.text(-box[1], box[0], CLUTTER_KINDS[kind], fontsize=6, color="0.35", ha="center")
    for box, lab, vel in zip(s.gt_boxes.numpy(), s.gt_labels.tolist(), s.gt_velocity.numpy()):
        c = box_corners(box)[0, [0, 2, 6, 4, 0]]
        ax1.plot(-c[:, 1], c[:, 0], "-", color=_CLASS_COLOURS[lab], lw=1.5)
        if np.any(vel):
            ax1.arrow(-box[1], box[0], -vel[1] * 0.4, vel[0] * 0.4, width=0.05, head_width=0.35, color=_CLASS_COLOURS[lab])
    ax1.scatter(-pts[:, 1], pts[:, 0], c=pts[:, 5], cmap="coolwarm", vmin=-vmax, vmax=vmax, s=5)
    ax1.scatter(-pts[blurred, 1], pts[blurred, 0], marker="x", c="magenta", s=8, linewidths=0.6)
    x0, y0, _, x1, y1, _ = cfg.point_cloud_range
    ax1.plot([0], [0], "k^", ms=6)
    ax1.set_xlim(-y1, -y0)
    ax1.set_ylim(x0, x1)
    ax1.set_aspect("equal")
    ax1.set_xlabel("-y (m)", fontsize=8)
    ax1.set_ylabel("x (m)", fontsize=8)
    ax1.tick_params(labelsize=7)
    handles = [plt.Line2D([], [], color=c, lw=1.5, label=n) for c, n in zip(_CLASS_COLOURS, CLASS_NAMES)]
    handles.append(plt.Line2D([], [], color="0.45", ls="--", label="clutter"))
    ax1.legend(handles=handles, fontsize=7, loc="upper left")
    ax1.set_title("BEV, points coloured by v_rc (m/s)", fontsize=9)
    fig.colorbar(sc, ax=ax1, fraction=0.04, pad=0.02).ax.tick_params(labelsize=7)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    plt.close(fig)
    # A 256-colour palette keeps the noisy camera panels small enough for the docs.
    from PIL import Image

    buf.seek(0)
    Image.open(buf).convert("RGB").quantize(colors=256, dither=Image.Dither.NONE).save(out, optimize=True)
    return out


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="scene.png")
    parser.add_argument("--lighting", choices=("normal", "dark", "dazzle"), default=None)
    parser.add_argument("--scans", type=int, default=5)
    parser.add_argument("--dpi", type=int, default=80)
    parser.add_argument("--lighting-row", action="store_true", help="add the image under all three lightings")
    args = parser.parse_args(argv)
    print(render_scene_png(args.seed, args.out, args.lighting, args.scans, args.dpi, args.lighting_row))


if __name__ == "__main__":
    main()
