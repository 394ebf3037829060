"""MSSF detectors: SECOND, CenterPoint, VoxelNeXt and PointPillars with multi-stage fusion blocks.

Each detector is ``image branch (or precomputed features) -> voxelisation / pillarisation -> backbone
with n fusion blocks and the semantic-guided head -> neck -> detection head``. In training mode
``forward(batch)`` returns the losses (``L = L_seg + L_det``, paper eq. 11 with unit weights); in eval
mode it returns per-sample detections.

    >>> from mssf_examples.models.presets import TINY
    >>> model = build_detector("centerpoint", TINY, num_fusion_blocks=2)  # doctest: +SKIP
"""

from __future__ import annotations

from typing import Dict, List, Optional, Sequence

import torch
from torch import Tensor, nn

from mssf_blocks.torch_versions import autocast_off
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.geometry import voxel_centroids
from mssf_blocks.samplers import FusionInputs

from ..data.batch import RadarCameraBatch
from .backbones import (
    BackboneOutput,
    CenterPointBackbone,
    PointPillarsBackbone,
    SECONDBackbone,
    VoxelNeXtBackbone,
)
from .heads import AnchorHead, BEVGrid, CenterHead, SparseCenterHead
from .image_branch import ImageBranch
from .presets import DetectorPreset
from .voxelize import DynamicVoxelizer, VoxelGrid

__all__ = ["BEVBackbone2D", "MSSFDetector", "build_detector", "DETECTOR_NAMES", "IMAGE_FEATURE_SOURCES"]

DETECTOR_NAMES = ("second", "centerpoint", "voxelnext", "pointpillars")
#: The authors' image normalisation (``data_preprocessor`` of their configs, after ``bgr_to_rgb``), applied
#: to ``batch.images`` (RGB in [0, 1]) by a detector built with ``layout="authors"``.
AUTHORS_IMAGE_MEAN = (123.675, 116.28, 103.53)
AUTHORS_IMAGE_STD = (58.395, 57.12, 57.375)
IMAGE_FEATURE_SOURCES = ("backbone", "precomputed")


def _bn2d(c: int) -> nn.Module:
    return nn.BatchNorm2d(c, eps=1e-3, momentum=0.01)


class BEVBackbone2D(nn.Module):
    """OpenPCDet's ``BaseBEVBackbone`` with two blocks (strides 1, 2) and upsampling to stride 1.

    Shapes:
        - bev ``(B, C_in, H, W)`` -> ``(B, sum(upsample_filters), H, W)`` (``H, W`` even).
    """

    def __init__(self, in_channels: int, layer_nums: Sequence[int], filters: Sequence[int], upsample_filters: Sequence[int]):
        super().__init__()
        self.blocks, self.deblocks = nn.ModuleList(), nn.ModuleList()
        cin = in_channels
        for i, (n, c, u) in enumerate(zip(layer_nums, filters, upsample_filters)):
            s = 1 if i == 0 else 2
            layers = [nn.ZeroPad2d(1), nn.Conv2d(cin, c, 3, stride=s, bias=False), _bn2d(c), nn.ReLU()]
            for _ in range(n):
                layers += [nn.Conv2d(c, c, 3, padding=1, bias=False), _bn2d(c), nn.ReLU()]
            self.blocks.append(nn.Sequential(*layers))
            self.deblocks.append(nn.Sequential(nn.ConvTranspose2d(c, u, s, stride=s, bias=False), _bn2d(u), nn.ReLU()))
            cin = c
        self.out_channels = sum(upsample_filters)

    def forward(self, x: Tensor) -> Tensor:
        ups = []
        for block, deblock in zip(self.blocks, self.deblocks):
            x = block(x)
            ups.append(deblock(x))
        h, w = ups[0].shape[-2:]
        return torch.cat([u[..., :h, :w] for u in ups], 1)


def _anchor_thresholds(class_names: Sequence[str]):
    # OpenPCDet KITTI: cars (and trucks) 0.6 / 0.45, pedestrians and cyclists 0.5 / 0.35.
    big = [n.lower() in ("car", "truck") for n in class_names]
    return tuple(0.6 if b else 0.5 for b in big), tuple(0.45 if b else 0.35 for b in big)


class MSSFDetector(nn.Module):
    """One of the four example detectors with ``n`` fusion blocks (``n = 0``: radar only).

    Args:
        name: ``"second"``, ``"centerpoint"``, ``"voxelnext"`` or ``"pointpillars"``.
        preset: a :class:`~mssf_examples.models.presets.DetectorPreset`.
        num_fusion_blocks: ``n`` (0..4; 0..3 for PointPillars, which has three 2D blocks).
        fusion: ``"msdff"`` or ``"sff"``.
        fusion_position: ``"before_residual"`` or ``"after_residual"``.
        head_position: where the semantic head reads the last fusion block's voxels: ``"after_fusion"``
            (the paper's and the authors' place, before the block's residual blocks) or
            ``"after_residual"`` (voxel backbones only; PointPillars' head always reads the fused voxels).
        pillar_layout: PointPillars only: ``"paper"`` (:class:`PointPillarsBackbone`, ``n`` fusion blocks
            replacing) or ``"authors"`` (:class:`AuthorsPointPillarsBackbone`: the authors' MSSF-PP, two
            concatenating fusion stages, their widths; ``num_fusion_blocks`` must be 2 and ``fusion``
            ``"msdff"``; loads their checkpoints through ``mssf_examples.models.authors_checkpoint``).
        layout: ``"paper"`` or ``"authors"``: the whole detector as the MSSF authors built it, for their
            checkpoints (``mssf_examples.models.authors_checkpoint``): PointPillars = ``pillar_layout="authors"``
            and their ``Anchor3DHead`` (:func:`~mssf_examples.models.heads.authors.authors_anchor_head_kwargs`:
            yaws 0 / 1.57, mmdet3d's direction offsets, their test settings); VoxelNeXt = the backbone's
            ``authors_layout`` and their ``VoxelNeXtHead``
            (:class:`~mssf_examples.models.heads.authors.AuthorsVoxelNeXtHead`, 256 wide). The preset gives the
            anchors (their anchor centres: :func:`~mssf_examples.models.heads.authors.authors_anchor_z_centers`)
            and the image branch (theirs: ResNet-50, FPN of 256 with 5 levels); their decoding settings
            (``test_cfg``) are :data:`~mssf_examples.models.heads.authors.AUTHORS_DECODE`, for
            ``score_threshold``, ``nms_iou``, ``max_detections`` (``convert-authors`` stores them). The
            images are normalised as theirs (:data:`AUTHORS_IMAGE_MEAN`, :data:`AUTHORS_IMAGE_STD` on 0..255).
        image_features: ``"backbone"`` runs the image branch on ``batch.images``; ``"precomputed"`` takes
            ``batch.image_features`` (``L`` levels of ``fpn_channels``), as with the paper's frozen branch.
        score_threshold, nms_iou, max_detections: decoding settings in eval mode.
        decode_options: the head's further decoding switches (its ``DECODE_OPTIONS``: ``multi_class`` for
            the anchor heads, ``class_agnostic_nms`` and ``center_range`` for VoxelNeXt); ``None``: none
            for ``layout="paper"``, the authors' for ``layout="authors"``
            (:func:`~mssf_examples.models.heads.authors.authors_decode_options`).

    ``forward(batch: RadarCameraBatch)`` returns, in training mode, a dict of scalar losses with
    ``"loss"`` the total (``det_*`` from the head, ``seg`` from the semantic-guided head when ``n > 0``)
    and, in eval mode, a list of ``B`` dicts ``boxes (K, 7)``, ``scores (K,)``, ``labels (K,)``.
    """

    def __init__(
        self,
        name: str,
        preset: DetectorPreset,
        num_fusion_blocks: int = 2,
        fusion: str = "msdff",
        fusion_position: str = "before_residual",
        image_features: str = "backbone",
        score_threshold: float = 0.1,
        nms_iou: Optional[float] = 0.5,
        max_detections: int = 100,
        head_position: str = "after_fusion",
        pillar_layout: str = "paper",
        layout: str = "paper",
        decode_options: Optional[dict] = None,
    ) -> None:
        super().__init__()
        if layout not in ("paper", "authors"):
            raise MSSFError(f"layout: expected 'paper' or 'authors', got {layout!r}")
        if layout == "authors":
            if name not in ("pointpillars", "voxelnext"):
                raise MSSFError(f"layout: 'authors' exists for their MSSF-PP (pointpillars) and MSSF-V (voxelnext), "
                                f"got name={name!r}")
            if name == "pointpillars":
                pillar_layout = "authors"
        self.layout = layout
        if name not in DETECTOR_NAMES:
            raise MSSFError(f"name: expected one of {DETECTOR_NAMES}, got {name!r}")
        if image_features not in IMAGE_FEATURE_SOURCES:
            raise MSSFError(f"image_features: expected one of {IMAGE_FEATURE_SOURCES}, got {image_features!r}")
        if not isinstance(preset, DetectorPreset):
            raise MSSFError(f"preset: expected a DetectorPreset, got {type(preset).__name__}")
        self.name, self.preset, self.image_feature_source = name, preset, image_features
        self.num_fusion_blocks = num_fusion_blocks
        self.score_threshold, self.nms_iou, self.max_detections = score_threshold, nms_iou, max_detections
        p = preset
        c_in = p.num_point_features
        image_channels = [p.fpn_channels] * p.num_image_levels
        fusion_kwargs = dict(
            num_fusion_blocks=num_fusion_blocks, fusion=fusion, fusion_position=fusion_position,
            image_channels=image_channels, msdff_heads=p.msdff_heads, msdff_points=p.msdff_points,
            msdff_value_projection=p.msdff_value_projection, seg_hidden=p.seg_hidden,
            msdff_value_dim=p.msdff_value_dim,
        )
        self.image_branch = None
        if num_fusion_blocks and image_features == "backbone":
            self.image_branch = ImageBranch(p.image_depth, p.image_base_channels, p.fpn_channels, p.num_image_levels,
                                            frozen=p.freeze_image_branch)
        self.voxelizer = None
        self.neck = None
        x0, y0, _, x1, y1, _ = p.point_cloud_range
        if name == "pointpillars" and head_position != "after_fusion":
            raise MSSFError(f"head_position: PointPillars' semantic head reads the fused lift voxels; expected "
                            f"'after_fusion', got {head_position!r}")
        if pillar_layout not in ("paper", "authors"):
            raise MSSFError(f"pillar_layout: expected 'paper' or 'authors', got {pillar_layout!r}")
        if pillar_layout == "authors" and (name != "pointpillars" or num_fusion_blocks != 2 or fusion != "msdff"):
            raise MSSFError(f"pillar_layout: 'authors' is their MSSF-PP (pointpillars, 2 MSDFF stages), got name={name!r}, "
                            f"num_fusion_blocks={num_fusion_blocks}, fusion={fusion!r}")
        if name == "pointpillars":
            grid = VoxelGrid(voxel_size=(p.pillar_size[0], p.pillar_size[1], p.pillar_range[5] - p.pillar_range[2]), point_cloud_range=p.pillar_range)
            if pillar_layout == "authors":
                from .backbones import AuthorsPointPillarsBackbone

                self.backbone = AuthorsPointPillarsBackbone(c_in, grid, image_channels, lift_z_size=p.lift_z_size,
                                                            msdff_heads=p.msdff_heads, msdff_points=p.msdff_points,
                                                            seg_hidden=p.seg_hidden)
            else:
                self.backbone = PointPillarsBackbone(
                    c_in, grid, lift_z_size=p.lift_z_size, pfn_channels=p.pfn_channels,
                    layer_nums=p.pillar_layer_nums, num_filters=p.pillar_filters,
                    num_upsample_filters=p.pillar_upsample_filters, **fusion_kwargs,
                )
            px0, py0, _, px1, py1, _ = p.pillar_range
            bev_grid = BEVGrid(px0, py0, px1, py1, *self.backbone.bev_shape)
            matched, unmatched = _anchor_thresholds(p.class_names)
            head_kw = {}
            if layout == "authors":
                from .heads.authors import authors_anchor_head_kwargs

                head_kw = authors_anchor_head_kwargs()
            self.head = AnchorHead(self.backbone.bev_channels, bev_grid, p.anchor_sizes, p.anchor_z_centers,
                                   matched_thresholds=matched, unmatched_thresholds=unmatched, **head_kw)
        else:
            grid = VoxelGrid(voxel_size=p.voxel_size, point_cloud_range=p.point_cloud_range)
            self.voxelizer = DynamicVoxelizer(p.point_cloud_range, p.voxel_size)
            fusion_kwargs["head_position"] = head_position
            if name == "voxelnext":
                self.backbone = VoxelNeXtBackbone(c_in, grid, channels=p.voxelnext_channels, out_channels=p.voxelnext_out,
                                                  authors_layout=layout == "authors", **fusion_kwargs)
                bev_grid = BEVGrid(x0, y0, x1, y1, *self.backbone.bev_shape)
                if layout == "authors":
                    from .heads.authors import AuthorsVoxelNeXtHead

                    self.head = AuthorsVoxelNeXtHead(self.backbone.bev_channels, bev_grid, p.num_classes,
                                                     head_channels=self.backbone.bev_channels)
                else:
                    self.head = SparseCenterHead(self.backbone.bev_channels, bev_grid, p.num_classes,
                                                 head_channels=p.head_channels)
            else:
                if name == "second":
                    self.backbone = SECONDBackbone(c_in, grid, channels=p.second_channels, out_channels=p.second_out,
                                                   **fusion_kwargs)
                else:
                    self.backbone = CenterPointBackbone(c_in, grid, channels=p.centerpoint_channels,
                                                        out_channels=p.centerpoint_out, **fusion_kwargs)
                self.neck = BEVBackbone2D(self.backbone.bev_channels, p.bev_layer_nums, p.bev_filters, p.bev_upsample_filters)
                bev_grid = BEVGrid(x0, y0, x1, y1, *self.backbone.bev_shape)
                if name == "second":
                    matched, unmatched = _anchor_thresholds(p.class_names)
                    self.head = AnchorHead(self.neck.out_channels, bev_grid, p.anchor_sizes, p.anchor_z_centers,
                                           matched_thresholds=matched, unmatched_thresholds=unmatched)
                else:
                    self.head = CenterHead(self.neck.out_channels, bev_grid, p.num_classes, head_channels=p.head_channels)
        self.bev_grid = bev_grid
        if decode_options is None and layout == "authors":
            from .heads.authors import authors_decode_options

            decode_options = authors_decode_options("anchor" if name == "pointpillars" else "voxelnext",
                                                    p.point_cloud_range)
        if decode_options is not None and not isinstance(decode_options, dict):
            raise MSSFError(f"decode_options: expected None or a dict, got {type(decode_options).__name__}")
        decode_options = dict(decode_options or {})
        allowed = getattr(self.head, "DECODE_OPTIONS", ())
        unknown = sorted(set(decode_options) - set(allowed))
        if unknown:
            raise MSSFError(f"decode_options: expected keys among {allowed} ({type(self.head).__name__}), "
                            f"got {unknown}")
        if decode_options.get("center_range") is not None:
            from .heads.common import check_center_range

            check_center_range(decode_options["center_range"])
        self.decode_options = decode_options

    # -- pieces -------------------------------------------------------------------------------------
    def _image_features(self, batch: RadarCameraBatch) -> List[Tensor]:
        if self.image_feature_source == "precomputed":
            feats = batch.image_features
            if feats is None:
                raise MSSFError("batch.image_features: required with image_features='precomputed', got None")
            p = self.preset
            if len(feats) != p.num_image_levels or any(f.shape[2] != p.fpn_channels for f in feats):
                raise MSSFError(
                    f"batch.image_features: expected {p.num_image_levels} levels of {p.fpn_channels} channels, "
                    f"got {[tuple(f.shape) for f in feats]}"
                )
            return list(feats)
        if batch.images is None:
            raise MSSFError("batch.images: required with image_features='backbone', got None")
        images = batch.images
        if self.layout == "authors":  # their Det3DDataPreprocessor: RGB 0..255, minus mean, over std
            mean = images.new_tensor(AUTHORS_IMAGE_MEAN)[:, None, None]
            std = images.new_tensor(AUTHORS_IMAGE_STD)[:, None, None]
            images = (images * 255.0 - mean) / std
        return self.image_branch(images)

    def extract(self, batch: RadarCameraBatch):
        """Run everything up to the head: returns ``(head predictions, BackboneOutput, points, points_batch)``."""
        if not isinstance(batch, RadarCameraBatch):
            raise MSSFError(f"batch: expected a RadarCameraBatch, got {type(batch).__name__}")
        if batch.num_point_features != self.preset.num_point_features:
            raise MSSFError(
                f"batch.points: expected {self.preset.num_point_features} columns {self.preset.point_features}, "
                f"got {batch.num_point_features}"
            )
        pts, pb = batch.flat_points()
        b = batch.batch_size
        fusion_inputs = None
        if self.num_fusion_blocks:
            if batch.image_size is None:
                raise MSSFError("batch.image_size: required by the fusion blocks (give images or image_size)")
            fusion_inputs = FusionInputs(self._image_features(batch), batch.lidar2img, batch.image_size, pts[:, :3], pb,
                                         batch.points_to_sensor)
        if self.name == "pointpillars":
            out = self.backbone(pts, pb, b, fusion_inputs)
            preds = self.head(out.bev)
        else:
            out = self.backbone(self.voxelizer(pts, pb, b), fusion_inputs)
            if self.name == "voxelnext":
                feats, coords = out.sparse_bev
                preds = self.head(feats, coords, b)
            else:
                preds = self.head(self.neck(out.bev))
        return preds, out, pts, pb

    def seg_loss(self, out: BackboneOutput, pts: Tensor, pb: Tensor, gt_boxes: List[Tensor]) -> Tensor:
        """``L_seg``: focal loss of the semantic head on the centroids of the last fusion block's voxels."""
        v = out.seg_voxels
        centroids, _ = voxel_centroids(pts, pb, v.coords, v.spatial_shape, v.batch_size, v.voxel_size,
                                       v.point_range_min, v.stride)
        logits = _float32(out.seg_logits)  # float16 centroids would round 50 m coordinates to 3 cm
        return self.backbone.seg_head.loss_from_boxes(logits, centroids.to(logits.dtype), v.batch_index,
                                                      [g.to(centroids) for g in gt_boxes])

    def forward(self, batch: RadarCameraBatch):
        preds, out, pts, pb = self.extract(batch)
        # Under autocast the head's maps come out in float16 / bfloat16; its losses and box decoding run in
        # float32 (a float16 focal loss or box encoding of 50 m ranges overflows / rounds to NaN).
        preds = _float32(preds)
        with _autocast_disabled(pts.device.type):
            if not self.training:
                return self.head.decode(preds, self.score_threshold, self.nms_iou, self.max_detections,
                                        **self.decode_options)
            if batch.gt_boxes is None:
                raise MSSFError("batch.gt_boxes: required in training mode, got None")
            losses: Dict[str, Tensor] = {f"det_{k}": v for k, v in
                                         self.head.loss(preds, batch.gt_boxes, batch.gt_labels).items()}
            if out.seg_logits is not None:
                losses["seg"] = self.seg_loss(out, pts, pb, batch.gt_boxes)
            losses["loss"] = sum(losses.values())
        return losses

    def extra_repr(self) -> str:
        return (f"name={self.name!r}, preset={self.preset.name!r}, num_fusion_blocks={self.num_fusion_blocks}, "
                f"image_features={self.image_feature_source!r}" + (", layout='authors'" if self.layout == "authors" else ""))


def _float32(x):
    """Floating tensors in ``x`` (nested dicts / lists / tuples) in float32 at least."""
    if isinstance(x, Tensor):
        return x.float() if x.is_floating_point() and x.dtype in (torch.float16, torch.bfloat16) else x
    if isinstance(x, dict):
        return {k: _float32(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_float32(v) for v in x)
    return x


def _autocast_disabled(device_type: str):
    return autocast_off(device_type)  # (torch-version dependent: mssf_blocks.torch_versions)


def build_detector(
    name: str,
    preset: DetectorPreset,
    num_fusion_blocks: int = 2,
    fusion: str = "msdff",
    fusion_position: str = "before_residual",
    image_features: str = "backbone",
    **kwargs,
) -> MSSFDetector:
    """Build ``"second" | "centerpoint" | "voxelnext" | "pointpillars"`` for ``preset``.

    ``num_fusion_blocks=0`` gives the radar-only baseline (no image branch, no semantic head).
    ``kwargs`` go to :class:`MSSFDetector` (``score_threshold``, ``nms_iou``, ``max_detections``).
    """
    return MSSFDetector(name, preset, num_fusion_blocks, fusion, fusion_position, image_features, **kwargs)
