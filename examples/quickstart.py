"""Quick start: MSSF fusion blocks on a generated radar + camera scene.

Builds a two-stage sparse backbone in which both stages are fusion blocks (stage 1: MSDFF with
QueryInit, stage 2: SFF), feeds it two synthetic VoD-like frames (radar points + camera image), and
prints what every step computed: voxels per stride, how many centroids hold points and land in the
image, the image features each stage added, the semantic head's foreground labels and scores, and
the forward/backward time. Untrained weights: the point is to show the blocks running on real shapes.

Run: ``python examples/quickstart.py [--seed 0] [--fusion msdff|sff]`` (needs the ``examples`` extra).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mssf_blocks import SparseVoxels, VoxelGrid  # noqa: E402
from mssf_blocks.blocks import FusionBlock  # noqa: E402
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit  # noqa: E402
from mssf_blocks.heads import SemanticGuidedHead, voxel_foreground_labels  # noqa: E402
from mssf_examples.models.image_branch import ImageBranch  # noqa: E402
from mssf_examples.scenes.synthetic import SceneConfig, generate_scene  # noqa: E402
from mssf_examples.models.spconv_helpers import enable_cpu_backward  # noqa: E402
from mssf_examples.models.voxelize import dynamic_voxelize  # noqa: E402


def sparse_stage(spconv, cin: int, cout: int, key: str):
    """An ordinary stage: strided SparseConv3d + BN + ReLU, then one SubMConv3d block."""
    down = spconv.SparseSequential(
        spconv.SparseConv3d(cin, cout, 3, stride=2, padding=1, bias=False, indice_key=f"down{key}"),
        nn.BatchNorm1d(cout), nn.ReLU())
    res = spconv.SparseSequential(
        spconv.SubMConv3d(cout, cout, 3, padding=1, bias=False, indice_key=f"subm{key}"),
        nn.BatchNorm1d(cout), nn.ReLU())
    return down, res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fusion", choices=("msdff", "sff"), default="msdff", help="sampler of stage 1")
    args = ap.parse_args(argv)
    try:
        import spconv.pytorch as spconv
    except ImportError:
        print("This example needs spconv: pip install 'mssf-blocks[examples]'", file=sys.stderr)
        return 2
    enable_cpu_backward()  # spconv 2.3 cannot run backward on CPU-only torch without it
    torch.manual_seed(args.seed)

    cfg = SceneConfig()
    scenes = [generate_scene(args.seed + i, cfg) for i in range(2)]
    grid = VoxelGrid(voxel_size=(0.1, 0.1, 0.125), point_cloud_range=cfg.point_cloud_range)
    points = torch.cat([s.points for s in scenes])
    points_batch = torch.cat([torch.full((len(s.points),), i, dtype=torch.long) for i, s in enumerate(scenes)])
    vox = dynamic_voxelize(points, points_batch, 2, grid)
    x = SparseVoxels(vox.features, vox.coords, grid.spatial_shape, 2, voxel_size=grid.voxel_size,
                     point_range_min=grid.point_range_min)
    print(f"scenes: {[len(s.points) for s in scenes]} radar points, {[len(s.gt_boxes) for s in scenes]} objects, "
          f"lighting {[s.lighting for s in scenes]}")
    print(f"voxels at stride 1: {x.num_voxels} on grid {x.spatial_shape} (D, H, W)")

    images = torch.stack([s.image for s in scenes])[:, None]  # (B, V=1, 3, H, W)
    image_branch = ImageBranch(depth=18, base_channels=16, fpn_channels=32, num_outs=4, frozen=True).eval()
    with torch.no_grad():
        levels = image_branch(images)
    print("image levels:", [tuple(l.shape) for l in levels])
    inputs = FusionInputs(
        image_features=levels, lidar2img=torch.stack([s.lidar2img for s in scenes]).float(),
        image_size=scenes[0].image_size, points=points[:, :3], points_batch=points_batch)

    c_in, c1, c2 = points.shape[1], 16, 32
    stem = spconv.SparseSequential(spconv.SubMConv3d(c_in, c1, 3, padding=1, bias=False, indice_key="stem"),
                                   nn.BatchNorm1d(c1), nn.ReLU())
    down1, res1 = sparse_stage(spconv, c1, c1, "1")
    down2, res2 = sparse_stage(spconv, c1, c2, "2")
    if args.fusion == "msdff":
        sampler1 = MSDFF(32, c1, num_heads=4, num_levels=4, num_points=4)
        query_init = QueryInit(c1, 32, c1, cfg.point_cloud_range)
    else:
        sampler1, query_init = SFF([32] * 4, c1), None
    stage1 = FusionBlock(sampler1, downsample=down1, blocks=res1, query_init=query_init)
    stage2 = FusionBlock(SFF([32] * 4, c2), downsample=down2, blocks=res2)
    head = SemanticGuidedHead(c2, hidden=(64, 64))

    t0 = time.perf_counter()
    h = SparseVoxels.from_spconv(stem(x.to_spconv()), x.grid, stride=(1, 1, 1))
    before1 = stage1.downsample(h.to_spconv())
    h1 = stage1(h, inputs)
    h2 = stage2(h1, inputs)
    weighted, scores, logits = head(h2, return_logits=True)
    t_fwd = time.perf_counter() - t0

    for name, block, v in (("stage 1", stage1, h1), ("stage 2", stage2, h2)):
        proj = block.projector(v, inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size)
        print(f"{name} ({type(block.fusion).__name__}): {v.num_voxels} voxels at stride {v.stride}, "
              f"{int(proj.has_points.sum())} hold radar points (the rest use their centre), "
              f"{int(proj.valid.any(1).sum())} project into the image")
    f_img = stage1.fuse(SparseVoxels.from_spconv(before1, x.grid, stride=(2, 2, 2)), inputs).features \
        - before1.features
    print(f"stage 1 image feature added: mean |f_img| = {f_img.abs().mean():.4f} "
          f"(voxels outside the image get exactly 0: {int((f_img.abs().sum(1) == 0).sum())} of them)")

    centroids = stage2.projector(h2, inputs.points, inputs.points_batch, inputs.lidar2img, inputs.image_size).centroid
    labels, ignore = voxel_foreground_labels(centroids, h2.batch_index, [s.gt_boxes for s in scenes])
    loss = head.loss(logits, labels, ignore)
    t0 = time.perf_counter()
    (weighted.features.square().mean() + loss).backward()
    t_bwd = time.perf_counter() - t0
    print(f"semantic head: {int(labels.sum())} foreground / {int(ignore.sum())} ignored / "
          f"{int((labels == 0).sum() - ignore.sum())} background voxels at stride 4; "
          f"scores mean {float(scores.detach().mean()):.3f} (untrained), focal loss {float(loss.detach()):.4f}")
    n_params = sum(p.numel() for m in (stage1, stage2, head) for p in m.parameters())
    print(f"output: {tuple(weighted.features.shape)} features; {n_params} fusion-backbone parameters; "
          f"forward {1e3 * t_fwd:.0f} ms, backward {1e3 * t_bwd:.0f} ms on CPU")
    return 0


if __name__ == "__main__":
    sys.exit(main())
