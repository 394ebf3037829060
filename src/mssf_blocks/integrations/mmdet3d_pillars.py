"""mmdet3d middle encoder running MSSF-PointPillars (pillar feature net, 2D blocks with fusion, deblocks).

PointPillars' fusion blocks act inside the 2D backbone (paper, "Extend to Pillar"): the BEV map of a
block is lifted into the radar points' voxels, fused with the image and summed back. The whole
PointPillars BEV path therefore sits behind one middle encoder that takes the points themselves
(``consumes_points = True``): ``MSSFDetector`` (``mssf_examples.mmdet3d.detector``) passes
the per-sample points instead of voxels (``Det3DDataPreprocessor(voxel=False)``, no
``pts_voxel_encoder``) and hands the output to ``pts_bbox_head`` directly (no ``pts_backbone`` /
``pts_neck``: the deblocks are mmdet3d's ``SECONDFPN``). The layers are those of
``mssf_examples.models.backbones.PointPillarsBackbone`` (imported when built; spconv is not needed).
"""

from __future__ import annotations

from typing import Any, List, Mapping, Optional, Sequence, Union

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations.mmdet3d import fusion_inputs_from_mmdet3d

__all__ = ["MSSFPillarEncoder"]


class MSSFPillarEncoder(nn.Module):
    """MSSF-PointPillars as an mmdet3d middle encoder: ``forward(points, img_features, batch_input_metas)``
    returns ``[bev (B, sum(num_upsample_filters), H / s0 * u0, W / s0 * u0)]`` (a one-level list, the
    contract of ``Anchor3DHead``).

    Args:
        in_channels: point features (VoD radar: 7).
        point_cloud_range: ``[x0, y0, z0, x1, y1, z1]``.
        voxel_size: pillar size ``[dx, dy, z1 - z0]`` (one z cell).
        lift_z_size: z size of the lift voxels of the fusion blocks.
        pfn_channels, layer_nums, layer_strides, num_filters, upsample_strides, num_upsample_filters:
            PointPillars' layers (mmdet3d's ``PillarFeatureNet`` / ``SECOND`` / ``SECONDFPN`` values).
        num_fusion_blocks, fusion, fusion_position, image_channels, msdff_heads, msdff_points,
        msdff_value_projection, msdff_value_dim, seg_hidden: the fusion blocks and the semantic head
            (``num_fusion_blocks=0``: the radar-only PointPillars).
        image_aug: see :func:`~mssf_blocks.integrations.mmdet3d.camera_from_meta`.
        layout: ``"paper"`` (default: ``PointPillarsBackbone``, the paper's fusion blocks inside the 2D blocks)
            or ``"authors"``: the MSSF authors' MSSF-PP module structure
            (``mssf_examples.models.backbones.AuthorsPointPillarsBackbone``: their ``PointPillarsScatterFuse`` and
            ``SECONDFuse`` stages with their forward switches, ``blocks`` / ``deblocks`` named as theirs), into
            which their released checkpoint loads (``python -m mssf_examples.mmdet3d convert-authors``). It is
            always their two MSDFF stages with the semantic head: ``num_fusion_blocks=2``, ``fusion="msdff"``,
            ``image_channels`` and ``seg_hidden`` given; ``msdff_value_projection`` / ``msdff_value_dim`` /
            ``fusion_position`` are not read.
    """

    consumes_points = True

    def __init__(
        self,
        in_channels: int,
        point_cloud_range: Sequence[float],
        voxel_size: Sequence[float],
        lift_z_size: float = 0.125,
        pfn_channels: int = 64,
        layer_nums: Sequence[int] = (3, 5, 5),
        layer_strides: Sequence[int] = (2, 2, 2),
        num_filters: Sequence[int] = (64, 128, 256),
        upsample_strides: Sequence[int] = (1, 2, 4),
        num_upsample_filters: Sequence[int] = (128, 128, 128),
        num_fusion_blocks: int = 1,
        fusion: str = "msdff",
        fusion_position: str = "before_residual",
        image_channels: Optional[Sequence[int]] = None,
        msdff_heads: int = 8,
        msdff_points: int = 4,
        msdff_value_projection: str = "after_sampling",
        msdff_value_dim: Union[int, str, None] = None,
        seg_hidden: Optional[Sequence[int]] = (256, 256),
        image_aug: str = "meta",
        layout: str = "paper",
    ) -> None:
        super().__init__()
        if layout not in ("paper", "authors"):
            raise MSSFError(f"layout: expected 'paper' or 'authors', got {layout!r}")
        try:
            from mssf_examples.models.backbones import AuthorsPointPillarsBackbone, PointPillarsBackbone
            from mssf_blocks.voxel_grid import VoxelGrid
        except ImportError as exc:
            raise ImportError("MSSFPillarEncoder is built from mssf_examples.models.backbones: install the examples "
                              "package (README, 'examples')") from exc
        pcr = [float(v) for v in point_cloud_range]
        vs = [float(v) for v in voxel_size]
        if len(pcr) != 6 or len(vs) != 3:
            raise MSSFError(f"point_cloud_range, voxel_size: expected 6 and 3 values, got {pcr} and {vs}")
        if abs((pcr[5] - pcr[2]) - vs[2]) > 1e-6:
            raise MSSFError(f"voxel_size: a pillar spans the whole z range {pcr[5] - pcr[2]:g} m, got z size {vs[2]:g}")
        self.in_channels = int(in_channels)
        self.layout = layout
        grid = VoxelGrid(voxel_size=tuple(vs), point_cloud_range=tuple(pcr))
        levels = None if image_channels is None else [int(c) for c in image_channels]
        seg = None if seg_hidden is None else tuple(int(c) for c in seg_hidden)
        blocks = dict(lift_z_size=float(lift_z_size), pfn_channels=int(pfn_channels), layer_nums=tuple(layer_nums),
                      layer_strides=tuple(layer_strides), upsample_strides=tuple(upsample_strides),
                      msdff_heads=int(msdff_heads), msdff_points=int(msdff_points), seg_hidden=seg)
        if layout == "authors":
            if int(num_fusion_blocks) != 2 or fusion != "msdff" or levels is None or seg is None:
                raise MSSFError(f"layout: 'authors' is their MSSF-PP (2 MSDFF stages with the semantic head), got "
                                f"num_fusion_blocks={num_fusion_blocks}, fusion={fusion!r}, image_channels="
                                f"{image_channels}, seg_hidden={seg_hidden}")
            self.net = AuthorsPointPillarsBackbone(self.in_channels, grid, levels, out_channels=tuple(num_filters),
                                                   upsample_channels=tuple(num_upsample_filters), **blocks)
        else:
            self.net = PointPillarsBackbone(
                self.in_channels, grid, num_filters=tuple(num_filters),
                num_upsample_filters=tuple(num_upsample_filters), num_fusion_blocks=int(num_fusion_blocks),
                fusion=fusion, fusion_position=fusion_position,
                image_channels=levels, msdff_value_projection=msdff_value_projection, msdff_value_dim=msdff_value_dim,
                **blocks)
        self.image_channels = None if image_channels is None else [int(c) for c in image_channels]
        self.image_aug = image_aug
        self.last_output = None

    @property
    def num_fusion_blocks(self) -> int:
        return 2 if self.layout == "authors" else self.net.num_fusion_blocks

    def forward(self, points: Sequence[Tensor], img_features: Optional[Sequence[Tensor]] = None,
                batch_input_metas: Optional[Sequence[Mapping]] = None, **kwargs: Any) -> List[Tensor]:
        if isinstance(points, Tensor) or not isinstance(points, (list, tuple)) or not points:
            raise MSSFError(f"points: expected a non-empty list of (P_i, C) tensors, got {type(points).__name__}")
        for i, p in enumerate(points):
            if p.dim() != 2 or p.shape[1] != self.in_channels:
                raise MSSFError(f"points[{i}]: expected (P, in_channels={self.in_channels}) (the pipeline's "
                                f"use_dim), got {tuple(p.shape)}")
        inputs = None
        if self.num_fusion_blocks:
            missing = [n for n, v in (("img_features", img_features), ("batch_input_metas", batch_input_metas)) if v is None]
            if missing:
                raise MSSFError(f"{', '.join(missing)}: required by the fusion blocks (num_fusion_blocks="
                                f"{self.num_fusion_blocks}); the detector must pass the image features and metainfo")
            inputs = fusion_inputs_from_mmdet3d(points, img_features, batch_input_metas, image_aug=self.image_aug)
        flat = torch.cat(list(points), 0)
        batch = torch.cat([torch.full((p.shape[0],), i, dtype=torch.long, device=flat.device) for i, p in enumerate(points)])
        out = self.net(flat, batch, len(points), inputs)
        self.last_output = out if out.seg_logits is not None else None
        return [out.bev]

    def seg_loss(self, points: Sequence[Tensor], gt_bboxes_3d: Sequence[Any]) -> Tensor:
        """The semantic head's focal loss of the latest forward (mmdet3d bottom-centre boxes)."""
        if self.last_output is None:
            raise MSSFError("seg_loss: no semantic-head output; build with seg_hidden and num_fusion_blocks > 0, then run forward")
        from mssf_blocks.integrations._common import mmdet3d_seg_loss

        return mmdet3d_seg_loss(self.net.seg_head, self.last_output, points, gt_bboxes_3d)
