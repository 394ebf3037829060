"""The MSSF authors' detection heads (``EricLiuhhh/MSSF``), for their checkpoints.

* MSSF-PP: mmdet3d's ``Anchor3DHead`` (three 1x1 convolutions ``conv_cls``, ``conv_reg``,
  ``conv_dir_cls`` on the 384-channel BEV) is :class:`~mssf_examples.models.heads.AnchorHead` with the settings
  of :func:`authors_anchor_head_kwargs`: anchor yaws ``(0, 1.57)`` (not ``pi / 2``), direction offset
  ``-pi / 2`` and limit offset 0 (mmdet3d's), their anchor bottoms (the anchor centre ``z`` is the
  bottom plus half the height: their ``DeltaXYZWLHRBBoxCoder`` lifts both boxes by half their height,
  so it is OpenPCDet's residual code on box centres), and their test settings (score > 0.1, 100 boxes
  before NMS, NMS IoU 0.01, 50 boxes). Only the class order differs: theirs
  :data:`AUTHORS_CLASS_ORDER`, the examples' the preset's; the converter permutes the output channels.
* MSSF-V: their ``VoxelNeXtHead`` with ``SeparateHeadVoxelNeXt`` is :class:`AuthorsVoxelNeXtHead`: no
  shared layer (their ``shared_conv`` sits in the encoder), one branch per output, each a 3x3
  ``SubMConv2d`` with bias, ``BatchNorm1d`` (eps 1e-5), ReLU, then a 1x1 ``SubMConv2d`` with bias. The
  branches ``heatmap, reg, height, dim, rot`` are the examples' ``hm, center, center_z, dim, rot`` (the
  same code: offset from the voxel's integer index, centre ``z``, log sizes, ``(sin, cos)`` yaw). Its
  convolutions run without spconv (:class:`SubMConv2dSpconvLayout`, spconv's parameters and results).

The detectors build these with ``MSSFDetector(..., layout="authors")``;
:func:`mssf_examples.models.authors_checkpoint.convert_authors` maps their tensors.
"""

from __future__ import annotations

import math
from typing import Dict, Sequence, Tuple

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

from .center_head import REGRESSION_BRANCHES
from .common import BEVGrid
from .sparse_center_head import SparseCenterHead

__all__ = ["AUTHORS_CLASS_ORDER", "AUTHORS_ANCHOR_BOTTOMS", "AUTHORS_DECODE", "AUTHORS_HEAD_NAMES",
           "authors_decode_options",
           "AuthorsVoxelNeXtHead", "SubMConv2dSpconvLayout", "authors_anchor_head_kwargs",
           "authors_anchor_z_centers", "class_permutation", "submanifold_neighbours"]

#: Their class order (``class_names`` of ``vod-3d-3class`` and ``tj4d-3d-4class``); label ``k`` of their
#: heads is ``AUTHORS_CLASS_ORDER[k]``.
AUTHORS_CLASS_ORDER = ("Pedestrian", "Cyclist", "Car", "Truck")

#: Their anchor bottoms (``AlignedAnchor3DRangeGenerator.ranges`` z) per class: VoD
#: ``pointpillars_hv_secfpn_vod_mm_backbone``, TJ4D ``pointpillars_hv_secfpn_tj4d_mm_backbone``.
AUTHORS_ANCHOR_BOTTOMS: Dict[str, Dict[str, float]] = {
    "vod": {"Pedestrian": -0.6, "Cyclist": -0.6, "Car": -1.78},
    "tj4d": {"Pedestrian": -1.163, "Cyclist": -1.353, "Car": -1.363, "Truck": -1.403},
}

#: Their ``SeparateHeadVoxelNeXt`` branch -> the examples' centre-head branch.
AUTHORS_HEAD_NAMES = (("heatmap", "hm"), ("reg", "center"), ("height", "center_z"), ("dim", "dim"), ("rot", "rot"))


def class_permutation(ours: Sequence[str], theirs: Sequence[str] = AUTHORS_CLASS_ORDER) -> Tuple[int, ...]:
    """``perm[k]`` = the index in ``theirs`` of our class ``ours[k]`` (names compared case-insensitively).

    ``theirs`` is truncated to ``len(ours)`` classes (their 3-class VoD and 4-class TJ4D orders share a prefix).
    """
    theirs = [t.lower() for t in theirs][: len(ours)]
    missing = [c for c in ours if c.lower() not in theirs]
    if missing or len(set(theirs)) != len(ours):
        raise MSSFError(f"class names: expected the classes {tuple(theirs)} in any order, got {tuple(ours)}")
    return tuple(theirs.index(c.lower()) for c in ours)


def authors_anchor_z_centers(class_names: Sequence[str], anchor_sizes: Sequence[Sequence[float]],
                             dataset: str) -> Tuple[float, ...]:
    """Their anchor centre ``z`` per class of ``class_names``: bottom + height / 2."""
    if dataset not in AUTHORS_ANCHOR_BOTTOMS:
        raise MSSFError(f"dataset: expected one of {tuple(AUTHORS_ANCHOR_BOTTOMS)}, got {dataset!r}")
    bottoms = {k.lower(): v for k, v in AUTHORS_ANCHOR_BOTTOMS[dataset].items()}
    if any(c.lower() not in bottoms for c in class_names):
        raise MSSFError(f"class_names: expected classes among {tuple(AUTHORS_ANCHOR_BOTTOMS[dataset])}, "
                        f"got {tuple(class_names)}")
    return tuple(bottoms[c.lower()] + float(s[2]) / 2 for c, s in zip(class_names, anchor_sizes))


def authors_anchor_head_kwargs() -> dict:
    """:class:`~mssf_examples.models.heads.AnchorHead` keyword arguments of their ``Anchor3DHead`` (besides
    channels, grid, sizes, centres): yaws, direction bins and the test settings of their config."""
    return dict(rotations=(0.0, 1.57), dir_offset=-math.pi / 2, dir_limit_offset=0.0, num_dir_bins=2,
                encode_angle_by_sincos=False, use_direction_classifier=True, nms_pre=100)


#: Their ``test_cfg`` decode settings ``(score_threshold, nms_iou, max_detections)`` per head: MSSF-PP
#: ``score_thr 0.1, nms_thr 0.01, max_num 50``; MSSF-V (``vx_mm_r50_ablation_n2m4``) ``score_threshold 0.02,
#: nms_thr 0.2, post_max_size 83``.
AUTHORS_DECODE = {"anchor": (0.1, 0.01, 50), "voxelnext": (0.02, 0.2, 83)}


def authors_decode_options(head: str, point_cloud_range: Sequence[float]) -> dict:
    """The switches of their test-time decoding beyond :data:`AUTHORS_DECODE` (the head's ``decode``
    keywords; ``MSSFDetector(layout="authors")`` uses them unless given ``decode_options``):

    * ``"anchor"`` (mmdet3d ``Anchor3DHead._predict_by_feat_single`` + ``box3d_multiclass_nms``):
      ``multi_class``: after the top ``nms_pre`` anchors by best class score, every class above the
      threshold gives a box.
    * ``"voxelnext"`` (their ``VoxelNeXtBBoxCoder.decode`` + ``VoxelNeXtHead.get_task_detections``):
      ``center_range``: their ``post_center_range`` (= their point-cloud range, the preset's here), and
      ``class_agnostic_nms``: one ``nms_bev`` over all classes.
    """
    if head == "anchor":
        return {"multi_class": True}
    if head == "voxelnext":
        return {"class_agnostic_nms": True, "center_range": tuple(float(v) for v in point_cloud_range)}
    raise MSSFError(f"head: expected one of {tuple(AUTHORS_DECODE)}, got {head!r}")


def submanifold_neighbours(coords: Tensor, ny: int, nx: int, kernel_size: int) -> Tensor:
    """``(k * k, M)`` row of the voxel at offset ``(dy, dx)`` (row-major, centre ``k // 2``) of every voxel
    ``coords (M, 3) (b, y, x)``, or ``-1`` where that cell is empty (a hash join: sort + searchsorted)."""
    c = coords.long()
    keys = (c[:, 0] * ny + c[:, 1]) * nx + c[:, 2]
    sorted_keys, order = keys.sort()
    r = kernel_size // 2
    rows = []
    for dy in range(kernel_size):
        for dx in range(kernel_size):
            y, x = c[:, 1] + dy - r, c[:, 2] + dx - r
            inside = (y >= 0) & (y < ny) & (x >= 0) & (x < nx)
            k = (c[:, 0] * ny + y) * nx + x
            pos = torch.searchsorted(sorted_keys, k).clamp(max=max(len(keys) - 1, 0))
            hit = inside & (sorted_keys[pos] == k) if len(keys) else inside
            rows.append(torch.where(hit, order[pos], torch.full_like(pos, -1)))
    return torch.stack(rows)


class SubMConv2dSpconvLayout(nn.Module):
    """A 2D submanifold convolution with spconv 2's parameters (``weight (out, k, k, in)``, ``bias``) and
    spconv 2.3's result, without spconv: output rows are the input rows; a ``k x k`` kernel reads the
    non-empty cells around each voxel (correlation, as ``SubMConv2d``); a 1x1 kernel computes
    ``x @ weight.view(in, out)``, what spconv's 1x1 path does with its default ``FILTER_HWIO = False``
    (it reads the ``(out, 1, 1, in)`` weight as ``(in, out)``: a reshape, not a transpose), so their
    trained 1x1 layers give their outputs."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, bias: bool = True):
        super().__init__()
        self.in_channels, self.out_channels, self.kernel_size = in_channels, out_channels, kernel_size
        self.weight = nn.Parameter(torch.empty(out_channels, kernel_size, kernel_size, in_channels))
        self.bias = nn.Parameter(torch.zeros(out_channels)) if bias else None
        nn.init.kaiming_normal_(self.weight)

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, bias={self.bias is not None}"

    def forward(self, x: Tensor, neighbours: Tensor) -> Tensor:
        """``x (M, in)``, ``neighbours`` from :func:`submanifold_neighbours` (ignored for ``k = 1``)."""
        if self.kernel_size == 1:
            out = x @ self.weight.reshape(self.in_channels, self.out_channels)
        else:
            out = x.new_zeros(x.shape[0], self.out_channels)
            padded = torch.cat([x, x.new_zeros(1, x.shape[1])])  # row -1: an empty cell reads zeros
            for t, rows in enumerate(neighbours):
                w = self.weight[:, t // self.kernel_size, t % self.kernel_size, :]
                out = out + padded[rows] @ w.T
        return out if self.bias is None else out + self.bias


class AuthorsVoxelNeXtHead(SparseCenterHead):
    """Their ``VoxelNeXtHead`` (one task, all classes): per branch ``SubMConv2d 3x3 (bias) -> BN1d -> ReLU
    -> SubMConv2d 1x1 (bias)`` on the sparse BEV voxels, no shared layer.

    The convolutions are :class:`SubMConv2dSpconvLayout` (spconv's parameters and results, in plain torch:
    any dtype, exact in float64; ``tests/examples/models/test_authors_heads.py`` checks them against spconv).

    Args:
        in_channels: voxel channels (theirs 256).
        grid: :class:`BEVGrid` of the voxels (VoD: 128 x 128 cells of 0.4 m).
        num_classes: ``K``.
        head_channels: the branches' hidden width (their ``share_conv_channel``, 256).
        kernel_size: of the branches' first convolution: 3 (theirs, VoxelNeXt's) or 1 (OpenPCDet's
            ``KERNEL_SIZE_HEAD: 1``).
        **kwargs: losses and decoding of :class:`SparseCenterHead`.

    Shape: as :class:`SparseCenterHead` (``forward(features (M, C), coords (M, 3) (b, y, x), batch_size)``).
    """

    def __init__(self, in_channels: int, grid: BEVGrid, num_classes: int, head_channels: int = 256,
                 kernel_size: int = 3, **kwargs):
        if kernel_size not in (1, 3):
            raise MSSFError(f"kernel_size: expected 3 (theirs, VoxelNeXt's) or 1, got {kernel_size!r}")
        super().__init__(in_channels, grid, num_classes, head_channels=head_channels, **kwargs)
        self.kernel_size = int(kernel_size)
        self.shared = nn.Identity()  # theirs has none (the encoder's shared_conv precedes the head)
        factory = {k: kwargs[k] for k in ("device", "dtype") if kwargs.get(k) is not None}
        outputs = [("hm", num_classes)] + list(REGRESSION_BRANCHES)
        self.heads = nn.ModuleDict({
            name: nn.Sequential(  # containers only: the names of their SparseSequential
                nn.Sequential(SubMConv2dSpconvLayout(in_channels, head_channels, self.kernel_size),
                              nn.BatchNorm1d(head_channels, eps=1e-5, momentum=0.1), nn.ReLU()),
                SubMConv2dSpconvLayout(head_channels, channels, 1))
            for name, channels in outputs}).to(**factory)
        for name, branch in self.heads.items():
            if name != "hm":
                nn.init.zeros_(branch[0][0].bias)
                nn.init.zeros_(branch[1].bias)
        nn.init.constant_(self.heads["hm"][1].bias, -2.19)

    def forward(self, features: Tensor, coords: Tensor, batch_size: int) -> Dict[str, object]:
        """Per-voxel heatmap logits and regression, as :meth:`SparseCenterHead.forward`."""
        self._check_inputs(features, coords, batch_size)
        neighbours = submanifold_neighbours(coords, self.grid.ny, self.grid.nx, self.kernel_size)
        out: Dict[str, object] = {}
        for name, branch in self.heads.items():
            conv, norm, act = branch[0]
            out[name] = branch[1](act(norm(conv(features, neighbours))), neighbours)
        out["coords"] = coords
        out["batch_size"] = batch_size
        return out
