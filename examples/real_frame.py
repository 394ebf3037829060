"""One real View-of-Delft frame through the library's projection and image samplers (no training).

Reads a KITTI-format radar frame (``mssf_examples.data.kitti_io``), voxelises the radar points on the VoD grid
of the paper (voxel 0.05 x 0.05 x 0.125 m; x 0..51.2, y -25.6..25.6, z -3..2 m), projects the voxel
centroids at strides 1, 2 and 4 with :class:`~mssf_blocks.VoxelCentroidProjector`, samples a small image
pyramid (average-pooled RGB at strides 4, 8, 16; no learned weights) with ``SFF`` and ``MSDFF`` from
``mssf_blocks.samplers``, prints what it computed and writes a PNG: the image with radar points coloured
by depth, labelled 2D boxes, projected 3D boxes and voxel centroids per stride, plus a bird's-eye view.

Needs the ``examples`` and ``plot`` extras (``pip install -e ".[examples,plot]"`` from a clone: matplotlib
draws the figure; without it the script says so and exits). Usage::

    python examples/real_frame.py --data-root ../shared/realdata/vod --frame 00549 --out /tmp/real_frame

The data is not part of this repository (VoD research-use licence): point ``--data-root`` at your copy
(layouts in ``docs/real-data.md``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Dict, List, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mssf_blocks import SparseVoxels, VoxelCentroidProjector  # noqa: E402
from mssf_examples.data.kitti_io import (  # noqa: E402
    VOD_CLASSES,
    VOD_RADAR,
    Frame,
    KittiFormatDataset,
    points_in_image,
    project_boxes_2d,
    sensor_box_corners,
)

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA_ROOT = REPO_ROOT.parent / "shared" / "realdata" / "vod"

#: VoD grid of the paper (x, y, z).
VOXEL_SIZE = (0.05, 0.05, 0.125)
POINT_RANGE = (0.0, -25.6, -3.0, 51.2, 25.6, 2.0)
STRIDES = (1, 2, 4)
IMAGE_STRIDES = (4, 8, 16)


def voxelize_mean(points: Tensor, voxel_size: Sequence[float], point_range: Sequence[float]) -> SparseVoxels:
    """Single-sample voxelisation: unique ``(0, z, y, x)`` voxels with the mean of their points' features.

    Points outside ``[min, max)`` of ``point_range`` are dropped (they belong to no voxel of the grid).
    """
    lo = torch.tensor(point_range[:3], dtype=points.dtype)
    hi = torch.tensor(point_range[3:], dtype=points.dtype)
    vs = torch.tensor(voxel_size, dtype=points.dtype)
    shape_xyz = [int(round((h - l) / v)) for l, h, v in zip(point_range[:3], point_range[3:], voxel_size)]
    inside = ((points[:, :3] >= lo) & (points[:, :3] < hi)).all(dim=1)
    pts = points[inside]
    idx = torch.floor((pts[:, :3] - lo) / vs).long()
    idx = torch.minimum(idx, torch.tensor(shape_xyz) - 1)  # float rounding at the upper bound
    zyx = idx[:, [2, 1, 0]]
    coords, inverse = torch.unique(zyx, dim=0, return_inverse=True)
    n = coords.shape[0]
    sums = torch.zeros(n, pts.shape[1], dtype=pts.dtype).index_add_(0, inverse, pts)
    counts = torch.zeros(n, dtype=pts.dtype).index_add_(0, inverse, torch.ones(len(pts), dtype=pts.dtype))
    coords4 = torch.cat([torch.zeros(n, 1, dtype=torch.long), coords], dim=1).int()
    return SparseVoxels(
        features=sums / counts[:, None], coords=coords4,
        spatial_shape=(shape_xyz[2], shape_xyz[1], shape_xyz[0]), batch_size=1,
        voxel_size=tuple(voxel_size), point_range_min=tuple(point_range[:3]),
    )


def coarsen(voxels: SparseVoxels, stride: int) -> SparseVoxels:
    """Voxels at ``stride`` (all three axes): unique ``coords // stride``, mean features."""
    if stride == 1:
        return voxels
    c = voxels.coords.long().clone()
    c[:, 1:] = torch.div(c[:, 1:], stride, rounding_mode="floor")
    coords, inverse = torch.unique(c, dim=0, return_inverse=True)
    n = coords.shape[0]
    feats = torch.zeros(n, voxels.features.shape[1], dtype=voxels.features.dtype).index_add_(0, inverse, voxels.features)
    counts = torch.zeros(n, dtype=feats.dtype).index_add_(0, inverse, torch.ones(len(inverse), dtype=feats.dtype))
    shape = tuple(-(-s // stride) for s in voxels.spatial_shape)
    return SparseVoxels(
        features=feats / counts[:, None], coords=coords.int(), spatial_shape=shape, batch_size=1,
        voxel_size=voxels.voxel_size, point_range_min=voxels.point_range_min, stride=(stride, stride, stride),
    )


def image_pyramid(image: Tensor, strides: Sequence[int]) -> List[Tensor]:
    """``(3, H, W)`` uint8 -> levels ``(1, 3, H/s, W/s)`` of average-pooled RGB in [0, 1]."""
    x = image.float()[None] / 255.0
    return [F.avg_pool2d(x, kernel_size=s, stride=s, ceil_mode=True) for s in strides]


def _stats(name: str, x: Tensor) -> str:
    if x.numel() == 0:
        return f"{name}: empty"
    return (f"{name}: shape {tuple(x.shape)} mean {x.mean():.4f} std {x.std():.4f} "
            f"min {x.min():.4f} max {x.max():.4f}")


def sample_features(pyramid: List[Tensor], projections: Dict[int, object], voxels: Dict[int, SparseVoxels],
                    seed: int) -> Dict[int, Dict[str, Tensor]]:
    """SFF and MSDFF outputs per stride (randomly initialised, eval mode: only the sampling matters)."""
    out: Dict[int, Dict[str, Tensor]] = {s: {} for s in projections}
    try:
        from mssf_blocks.samplers import MSDFF, SFF
    except ImportError as exc:
        print(f"mssf_blocks.samplers not available ({exc}); trying the plain bilinear sampler")
        try:
            from mssf_blocks.functional.sampling import bilinear_sample, camera_mean
        except ImportError as exc2:
            print(f"mssf_blocks.functional.sampling not available either ({exc2}); skipping image sampling")
            return out
        for s, proj in projections.items():
            parts = [camera_mean(bilinear_sample(lvl, proj.uv, proj.batch_index, proj.valid), proj.valid)
                     for lvl in pyramid]
            out[s]["rgb"] = torch.cat(parts, dim=1)
        return out
    torch.manual_seed(seed)
    chans = [int(p.shape[1]) for p in pyramid]
    embed = 8
    sff = SFF(chans, embed).eval()
    # The pyramid here is RGB (3 channels), which 2 heads cannot split: project the values to the voxel
    # width first (value_dim=embed), the narrow layout, instead of the paper's value_dim = value_channels.
    msdff = MSDFF(chans[0], embed, value_dim=embed, num_heads=2, num_levels=len(pyramid), num_points=4).eval()
    lift = torch.nn.Linear(VOD_RADAR.num_channels, embed)  # fixed random query from the voxel features
    with torch.no_grad():
        for s, proj in projections.items():
            out[s]["rgb"] = sff.sample(pyramid, proj)
            out[s]["sff"] = sff(pyramid, proj)
            out[s]["msdff"] = msdff(lift(voxels[s].features), pyramid, proj)
    return out


def _draw(frame: Frame, voxels: Dict[int, SparseVoxels], projections: Dict[int, object], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon, Rectangle

    h, w = frame.image_size
    fig = plt.figure(figsize=(20, 7.5))
    ax = fig.add_axes([0.01, 0.05, 0.62, 0.9])
    bev = fig.add_axes([0.70, 0.07, 0.28, 0.86])
    ax.imshow(frame.image.permute(1, 2, 0).numpy())
    ax.set_xlim(0, w - 1)
    ax.set_ylim(h - 1, 0)
    ax.set_title(f"VoD frame {frame.frame_id}: radar points (colour = depth), labelled 2D boxes (dashed), "
                 "projected 3D boxes, voxel centroids", fontsize=10)

    l2i = frame.lidar2img
    xyz1 = torch.cat([frame.points[:, :3].double(), torch.ones(len(frame.points), 1, dtype=torch.float64)], 1)
    cam = xyz1 @ l2i.T
    mask = points_in_image(frame.points, l2i, frame.image_size)
    uv = cam[mask, :2] / cam[mask, 2:3]
    sc = ax.scatter(uv[:, 0], uv[:, 1], c=cam[mask, 2], cmap="turbo", s=14, vmin=0, vmax=50,
                    edgecolors="black", linewidths=0.3, zorder=6)
    fig.colorbar(sc, ax=ax, fraction=0.02, pad=0.01, label="depth [m]")

    markers = {1: ("o", "white", 10), 2: ("s", "magenta", 28), 4: ("^", "yellow", 50)}
    for s, proj in projections.items():
        m, col, size = markers[s]
        v = proj.valid[:, 0]
        px = proj.uv[v, 0] * torch.tensor([w, h], dtype=proj.uv.dtype) - 0.5
        ax.scatter(px[:, 0], px[:, 1], marker=m, facecolors="none", edgecolors=col, s=size, linewidths=0.6,
                   label=f"centroids stride {s} ({int(v.sum())})", zorder=5)

    objects = frame.objects
    corners = sensor_box_corners(frame.boxes)
    _, in_front = project_boxes_2d(corners, l2i, frame.image_size)
    edges = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
    for i, name in enumerate(objects.names):
        if name == "DontCare":
            continue
        known = bool(frame.labels[i] >= 0)
        col = "lime" if known else "orange"
        left, top, right, bottom = objects.boxes_2d[i].tolist()
        ax.add_patch(Rectangle((left, top), right - left, bottom - top, fill=False, ec=col, ls="--", lw=1.0))
        ax.text(left, top - 4, name, color=col, fontsize=7)
        if in_front[i]:
            c = torch.cat([corners[i], torch.ones(8, 1, dtype=torch.float64)], 1) @ l2i.T
            p = c[:, :2] / c[:, 2:3]
            for a, b in edges:
                ax.plot([p[a, 0], p[b, 0]], [p[a, 1], p[b, 1]], color=col, lw=1.0, alpha=0.9)
    ax.legend(loc="lower left", fontsize=8, facecolor="gray", framealpha=0.6)
    ax.axis("off")

    # bird's-eye view: x forward (up), y left (to the left)
    pts = frame.points
    bev.scatter(-pts[:, 1], pts[:, 0], c=pts[:, 5], cmap="coolwarm", s=9, vmin=-5, vmax=5,
                edgecolors="black", linewidths=0.2)
    for i, name in enumerate(objects.names):
        if name == "DontCare":
            continue
        col = "green" if frame.labels[i] >= 0 else "orange"
        poly = corners[i, :4, :2]
        bev.add_patch(Polygon(torch.stack([-poly[:, 1], poly[:, 0]], 1).numpy(), closed=True, fill=False, ec=col))
        head = frame.boxes[i]
        tip = head[:2] + 0.5 * head[3] * torch.stack([head[6].cos(), head[6].sin()])
        bev.plot([-head[1], -tip[1]], [head[0], tip[0]], color=col, lw=1)
    bev.set_xlim(-POINT_RANGE[4], -POINT_RANGE[1])
    bev.set_ylim(POINT_RANGE[0], POINT_RANGE[3])
    bev.set_aspect("equal")
    bev.set_xlabel("-y [m] (left <-)")
    bev.set_ylabel("x [m] (forward)")
    bev.set_title("BEV: radar points (colour = v_r compensated), GT boxes (green: evaluated classes)", fontsize=9)
    bev.grid(alpha=0.3)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run(data_root: Path, frame_id: str, out_dir: Path, sensor: str = "radar", seed: int = 0) -> Dict[str, object]:
    """Compute and print everything; returns the numbers (for tests) and writes the PNG."""
    if not Path(data_root).is_dir():
        raise SystemExit(
            f"error: data root {data_root} not found. Pass --data-root pointing at a View-of-Delft folder "
            "(see docs/real-data.md); the data is licence-restricted and not shipped with this repository."
        )
    ds = KittiFormatDataset(data_root, VOD_RADAR, sensor=sensor, class_names=VOD_CLASSES)
    if frame_id not in ds.frame_ids:
        raise SystemExit(f"error: frame {frame_id!r} not found in {ds}; available e.g. {ds.frame_ids[:5]}")
    frame = ds.load(frame_id)
    h, w = frame.image_size
    n_img = int(points_in_image(frame.points, frame.lidar2img, frame.image_size).sum())
    print(f"frame {frame_id}: {frame.points.shape[0]} points x {frame.points.shape[1]} features "
          f"{VOD_RADAR.features}, image {w}x{h}, {n_img} points project inside the image")
    print(f"objects: {len(frame.objects)} labelled, {int((frame.labels >= 0).sum())} of {VOD_CLASSES}")

    base = voxelize_mean(frame.points, VOXEL_SIZE, POINT_RANGE)
    lo, hi = torch.tensor(POINT_RANGE[:3]), torch.tensor(POINT_RANGE[3:])
    n_range = int(((frame.points[:, :3] >= lo) & (frame.points[:, :3] < hi)).all(dim=1).sum())
    print(f"grid: voxel {VOXEL_SIZE} m, range {POINT_RANGE}: {n_range} points inside")
    projector = VoxelCentroidProjector(point_range_max=POINT_RANGE[3:])
    l2i = frame.lidar2img.float()[None]
    pts = frame.points
    batch = torch.zeros(len(pts), dtype=torch.long)
    voxels, projections, result = {}, {}, {"points": int(pts.shape[0]), "points_in_image": n_img}
    for s in STRIDES:
        vox = coarsen(base, s)
        proj = projector(vox, pts[:, :3], batch, l2i, frame.image_size)
        voxels[s], projections[s] = vox, proj
        n, k = int(vox.coords.shape[0]), int(proj.valid.sum())
        result[f"stride{s}"] = (n, k)
        print(f"stride {s}: voxels={n} valid={k} fraction_valid={k / max(n, 1):.4f} "
              f"with_points={int(proj.has_points.sum())} spatial_shape={vox.spatial_shape}")

    pyramid = image_pyramid(frame.image, IMAGE_STRIDES)
    print("image pyramid: " + ", ".join(f"stride {s}: {tuple(p.shape)}" for s, p in zip(IMAGE_STRIDES, pyramid)))
    feats = sample_features(pyramid, projections, voxels, seed)
    for s in STRIDES:
        for key, val in feats[s].items():
            print(f"stride {s} " + _stats(key, val) + f", zero rows {int((val == 0).all(dim=1).sum())}")
    result["features"] = feats

    png = Path(out_dir) / f"real_frame_{frame_id}.png"
    _draw(frame, voxels, projections, png)
    print(f"wrote {png}")
    result["png"] = png
    return result


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-root", type=Path, default=DEFAULT_DATA_ROOT,
                        help=f"VoD root (nested radar/training/... or flat radar/velodyne + image_2); default {DEFAULT_DATA_ROOT}")
    parser.add_argument("--frame", default="00549", help="frame id (default 00549)")
    parser.add_argument("--out", type=Path, default=Path("real_frame_output"), help="output folder for the PNG")
    parser.add_argument("--sensor", default="radar", help="radar, radar_3frames or radar_5frames")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:  # before any work: the figure needs matplotlib, which the examples extra does not install
        import matplotlib  # noqa: F401
    except ImportError:
        sys.exit("examples/real_frame.py draws its figure with matplotlib, which is not installed: "
                 "pip install \"mssf-blocks[plot]\" (from a clone: pip install -e \".[examples,plot]\")")
    run(args.data_root, args.frame, args.out, args.sensor, args.seed)


if __name__ == "__main__":
    main()
