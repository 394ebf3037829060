"""Dataset presets for the example detectors (paper Sec. "Implementation Details").

* :data:`VOD` — View-of-Delft, 5-scan radar: range ``0 < x < 51.2, -25.6 < y < 25.6, -3 < z < 2`` m,
  point features ``[x, y, z, RCS, v_r, v_rc, t]``, classes car / pedestrian / cyclist.
* :data:`TJ4D` — TJ4DRadSet, single scan: voxel range ``0 < x < 70.4, -40 < y < 40, -4 < z < 2``,
  pillar range ``0 < x < 69.12, -39.68 < y < 39.68, -4 < z < 2``, features ``[x, y, z, v_rc, Power]``,
  classes car / pedestrian / cyclist / truck.
* Both: voxel size ``(0.05, 0.05, 0.125)`` m, pillar size ``(0.16, 0.16)`` m; PointPillars anchors as the
  paper states (VoD: car (3.9, 1.6, 1.56), pedestrian (0.8, 0.6, 1.73), cyclist (1.76, 0.6, 1.73); TJ4D:
  car (1.84, 4.56, 1.70), pedestrian (0.6, 0.8, 1.69), cyclist (0.78, 1.77, 1.60), truck
  (2.66, 10.76, 3.47) printed as ``(w, l, h)`` and stored here as ``(dx, dy, dz) = (l, w, h)``, see
  :mod:`mssf_examples.models.heads.anchor_head`); VoxelNeXt channels doubled; MSDFF, ``n = 2`` by default.
* :data:`TINY` — a coarse grid, small images and few channels for CPU tests (not from the paper).

Values that the paper does not state are marked "not from the paper" in the field docs (network
widths follow the OpenPCDet KITTI configurations of the base detectors).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Tuple, Union

from .heads.anchor_head import TJ4D_ANCHOR_SIZES, VOD_ANCHOR_SIZES

__all__ = ["DetectorPreset", "VOD", "TJ4D", "TINY", "tiny_preset"]

Range6 = Tuple[float, float, float, float, float, float]


@dataclass(frozen=True)
class DetectorPreset:
    """Everything a detector needs to know about a dataset, plus the network widths.

    Attributes:
        name: preset name.
        point_cloud_range: voxel-based range ``(x0, y0, z0, x1, y1, z1)`` metres.
        voxel_size: ``(x, y, z)`` voxel size.
        pillar_range: pillar-based range (TJ4D uses a different one, divisible by the pillar size).
        pillar_size: ``(x, y)`` pillar size.
        point_features: names of the point columns (``x, y, z`` first).
        class_names: detection classes (label ``k`` is ``class_names[k]``).
        anchor_sizes: ``(dx, dy, dz)`` per class (anchor head).
        anchor_z_centers: anchor box-centre ``z`` per class. Not from the paper: OpenPCDet's KITTI
            anchor bottoms (car -1.78, others -0.6) plus half the anchor height.
        image_size: ``(H, W)`` of the network's image input.
        image_depth, image_base_channels, fpn_channels, num_image_levels, freeze_image_branch: the
            image branch (paper: ResNet-50 + FPN, 256 channels, frozen).
        second_channels, second_out: SECOND sparse backbone (stem, stage 1-4) and ``conv_out``.
        centerpoint_channels, centerpoint_out: CenterPoint sparse backbone.
        voxelnext_channels, voxelnext_out: VoxelNeXt (paper: doubled) stem + 6 stages, BEV channels.
        bev_layer_nums, bev_filters, bev_upsample_filters: 2D BEV backbone of SECOND / CenterPoint
            (strides 1, 2; upsample 1, 2). Not from the paper (OpenPCDet KITTI).
        pfn_channels, pillar_layer_nums, pillar_filters, pillar_upsample_filters: PointPillars.
        lift_z_size: z size of the voxels the pillar fusion lifts the BEV into (not from the paper:
            the voxel preset's z size).
        head_channels: hidden width of the centre heads.
        msdff_heads, msdff_points: MSDFF attention heads and points per level (Deformable DETR: 8, 4).
        msdff_value_projection: where MSDFF applies its value projection. Both orders give the same
            result (to rounding); with MSDFF's default ``method="auto"`` it picks the cheapest exact plan
            per level (project every pixel, project only the touched pixels, or sample then project)
            whatever the order, so this setting no longer changes the speed (see docs/fusion.md). Not
            from the paper.
        msdff_value_dim: MSDFF's ``value_dim``, the channels its heads attend over. ``None`` (default):
            ``fpn_channels`` (the paper's eq. 10 and the authors' code: ``value_proj`` 256 -> 256,
            ``output_proj`` 256 -> voxel channels); ``"voxel_channels"``: each block's voxel channels
            (the narrow layout of earlier releases); or an int.
        seg_hidden: hidden widths of the semantic-guided head (not in the paper; (256, 256) is the
            default of mmdet3d's ForegroundSegmentationHead, which the public MSSF code uses).
    """

    name: str
    point_cloud_range: Range6
    voxel_size: Tuple[float, float, float]
    pillar_range: Range6
    pillar_size: Tuple[float, float]
    point_features: Tuple[str, ...]
    class_names: Tuple[str, ...]
    anchor_sizes: Tuple[Tuple[float, float, float], ...]
    anchor_z_centers: Tuple[float, ...]
    image_size: Tuple[int, int]
    image_depth: int = 50
    image_base_channels: int = 64
    fpn_channels: int = 256
    num_image_levels: int = 4
    freeze_image_branch: bool = True
    second_channels: Tuple[int, ...] = (16, 16, 32, 64, 64)
    second_out: int = 128
    centerpoint_channels: Tuple[int, ...] = (16, 16, 32, 64, 128)
    centerpoint_out: int = 128
    voxelnext_channels: Tuple[int, ...] = (32, 32, 64, 128, 256, 256, 256)
    voxelnext_out: int = 256
    bev_layer_nums: Tuple[int, int] = (5, 5)
    bev_filters: Tuple[int, int] = (128, 256)
    bev_upsample_filters: Tuple[int, int] = (256, 256)
    pfn_channels: int = 64
    pillar_layer_nums: Tuple[int, int, int] = (3, 5, 5)
    pillar_filters: Tuple[int, int, int] = (64, 128, 256)
    pillar_upsample_filters: Tuple[int, int, int] = (128, 128, 128)
    lift_z_size: float = 0.125
    head_channels: int = 64
    msdff_heads: int = 8
    msdff_points: int = 4
    msdff_value_projection: str = "before_sampling"
    msdff_value_dim: Union[int, str, None] = None
    seg_hidden: Tuple[int, ...] = (256, 256)

    @property
    def num_point_features(self) -> int:
        return len(self.point_features)

    @property
    def num_classes(self) -> int:
        return len(self.class_names)


def _z_centres(sizes, bottoms):
    return tuple(round(b + s[2] / 2, 4) for s, b in zip(sizes, bottoms))


#: View-of-Delft (5 radar scans).
VOD = DetectorPreset(
    name="vod",
    point_cloud_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0),
    voxel_size=(0.05, 0.05, 0.125),
    pillar_range=(0.0, -25.6, -3.0, 51.2, 25.6, 2.0),
    pillar_size=(0.16, 0.16),
    point_features=("x", "y", "z", "RCS", "v_r", "v_rc", "t"),
    class_names=("Car", "Pedestrian", "Cyclist"),
    anchor_sizes=tuple(VOD_ANCHOR_SIZES),
    anchor_z_centers=_z_centres(VOD_ANCHOR_SIZES, (-1.78, -0.6, -0.6)),
    image_size=(1216, 1936),
)

#: TJ4DRadSet (single radar scan).
TJ4D = DetectorPreset(
    name="tj4d",
    point_cloud_range=(0.0, -40.0, -4.0, 70.4, 40.0, 2.0),
    voxel_size=(0.05, 0.05, 0.125),
    pillar_range=(0.0, -39.68, -4.0, 69.12, 39.68, 2.0),
    pillar_size=(0.16, 0.16),
    point_features=("x", "y", "z", "v_rc", "Power"),
    class_names=("Car", "Pedestrian", "Cyclist", "Truck"),
    anchor_sizes=tuple(TJ4D_ANCHOR_SIZES),
    anchor_z_centers=_z_centres(TJ4D_ANCHOR_SIZES, (-1.78, -0.6, -0.6, -1.78)),
    image_size=(640, 1280),
)


def tiny_preset(base: DetectorPreset = VOD, **changes) -> DetectorPreset:
    """A CPU-test-sized preset with ``base``'s features, classes and anchors (not from the paper).

    12.8 m x 12.8 m x 5 m, voxels ``(0.2, 0.2, 0.125)`` (64 x 64 x 40), pillars ``(0.2, 0.2)``,
    ``32 x 64`` images, ResNet-18 with 4 base channels, 8-channel FPN and a few channels everywhere.
    """
    z0, z1 = base.point_cloud_range[2], base.point_cloud_range[5]
    fields = dict(
        name=f"tiny-{base.name}",
        point_cloud_range=(0.0, -6.4, z0, 12.8, 6.4, z1),
        voxel_size=(0.2, 0.2, base.voxel_size[2]),
        pillar_range=(0.0, -6.4, z0, 12.8, 6.4, z1),
        pillar_size=(0.2, 0.2),
        image_size=(32, 64),
        image_depth=18,
        image_base_channels=4,
        fpn_channels=8,
        freeze_image_branch=False,
        second_channels=(8, 8, 8, 16, 16),
        second_out=16,
        centerpoint_channels=(8, 8, 8, 16, 16),
        centerpoint_out=16,
        voxelnext_channels=(8, 8, 8, 16, 16, 16, 16),
        voxelnext_out=16,
        bev_layer_nums=(1, 1),
        bev_filters=(16, 16),
        bev_upsample_filters=(16, 16),
        pfn_channels=8,
        pillar_layer_nums=(1, 1, 1),
        pillar_filters=(8, 16, 16),
        pillar_upsample_filters=(8, 8, 8),
        lift_z_size=0.5,
        head_channels=16,
        msdff_heads=2,
        msdff_points=2,
        seg_hidden=(16,),
    )
    fields.update(changes)
    return replace(base, **fields)


#: CPU-test preset (VoD features and classes).
TINY = tiny_preset(VOD)


# --------------------------------------------------------------------------------------------------
# Training recipes (docs/training.md): augmentation, optimiser and schedule, paper beside the authors' code
# --------------------------------------------------------------------------------------------------
from ..data.augment import AugmentationConfig  # noqa: E402  (below the presets: augment needs no preset)

__all__ += ["TrainingRecipe", "VOD_RECIPE", "TJ4D_RECIPE", "AUTHORS_TJ4D_VOXEL_SIZE", "authors_preset"]


@dataclass(frozen=True)
class TrainingRecipe:
    """How the paper / the authors' configs train a dataset (optimiser settings are ``train_detector``'s).

    Attributes:
        name: recipe name.
        augmentation: the global augmentation (paper: random flip, scaling, rotation; the authors'
            configs: flip p = 0.5 synchronised with the image, rotation +-pi/4, scaling 0.95-1.05, no
            translation).
        point_feature_kinds: ``(column name, kind)`` for every input point column, in order, named as the
            dataset's :class:`~mssf_examples.data.kitti_io.PointFormat` ``features`` (kinds:
            :data:`mssf_examples.data.augment.FEATURE_KINDS`).
        initial_lr: the learning rate as the paper and mmdet3d's cyclic schedule state it: the *start* of
            the one-cycle, whose peak is 10 x higher. :meth:`peak_lr` converts to ``train_detector``'s
            ``lr`` (the peak; start = peak / 10, end = peak / 1e5: the same curve).
        initial_lr_by_blocks: ``(n, lr)`` overrides for ``n`` fusion blocks, where the authors' config for
            that ``n`` differs from the paper.
        epochs: passes over the train split (the authors: 40 epochs of a twice-repeated dataset).
        batch_size: frames per step (the authors' configs: 8, one GPU).
        weight_decay, grad_clip: AdamW weight decay and gradient-norm clip (betas 0.95 / 0.99).
    """

    name: str
    augmentation: AugmentationConfig
    point_feature_kinds: Tuple[Tuple[str, str], ...]
    initial_lr: float
    initial_lr_by_blocks: Tuple[Tuple[int, float], ...] = ()
    epochs: float = 80.0
    batch_size: int = 8
    weight_decay: float = 0.01
    grad_clip: float = 10.0

    @property
    def feature_names(self) -> Tuple[str, ...]:
        return tuple(n for n, _ in self.point_feature_kinds)

    @property
    def feature_kinds(self) -> Tuple[str, ...]:
        return tuple(k for _, k in self.point_feature_kinds)

    def peak_lr(self, num_fusion_blocks: int) -> float:
        """``train_detector``'s ``lr`` (the one-cycle peak) for ``num_fusion_blocks``: 10 x the initial lr."""
        return 10.0 * dict(self.initial_lr_by_blocks).get(int(num_fusion_blocks), self.initial_lr)


#: View-of-Delft. Paper: AdamW, one-cycle, initial lr 1e-3. The authors' VoD configs use 1e-3 for n = 1
#: (``vx_mm_r50_ablation_n1m5``) but 5e-4 for n = 2 (``vx_mm_r50_ablation_n2m4``, the paper's default
#: model). Choice: the authors' value for n = 2 (5e-4, peak 5e-3), the paper's 1e-3 (peak 1e-2) otherwise.
#: Columns: VoD's radar files hold x, y, z, RCS, v_r, v_r_compensated, time (VoD devkit); all features are
#: scalars under a rotation about the sensor's z, a flip and a scaling.
VOD_RECIPE = TrainingRecipe(
    name="vod",
    augmentation=AugmentationConfig(),
    point_feature_kinds=(("x", "x"), ("y", "y"), ("z", "z"), ("rcs", "scalar"), ("v_r", "scalar"),
                         ("v_r_comp", "scalar"), ("time", "scalar")),
    initial_lr=1e-3,
    initial_lr_by_blocks=((2, 5e-4),),
)

#: TJ4DRadSet. Paper and the authors' TJ4D configs agree on the initial lr 1e-3 (peak 1e-2). Columns: the
#: files hold x, y, z, V_r, Range, Power, Alpha, Beta; the input is x, y, z, V_r, Power (scalars). To feed
#: Alpha (azimuth) add it with kind ``azimuth_deg`` / ``azimuth_rad`` after checking on your download that
#: it equals ``atan2(y, x)`` (sign and unit), and Beta (elevation) with kind ``elevation``.
TJ4D_RECIPE = TrainingRecipe(
    name="tj4d",
    augmentation=AugmentationConfig(),
    point_feature_kinds=(("x", "x"), ("y", "y"), ("z", "z"), ("v_r", "scalar"), ("power", "scalar")),
    initial_lr=1e-3,
)

#: The authors' TJ4D voxel size (``voxelnext_voxel005_vod_multimodal_r50pytorch_tj4d``: z 0.15 m); the paper
#: (and :data:`TJ4D`) states 0.125 m for both datasets.
AUTHORS_TJ4D_VOXEL_SIZE = (0.05, 0.05, 0.15)


def authors_preset(base: DetectorPreset) -> DetectorPreset:
    """``base`` with the authors' config where it differs from the paper (TJ4D voxel z 0.15 m; VoD: unchanged)."""
    if base.name == "tj4d":
        return replace(base, name="tj4d-authors", voxel_size=AUTHORS_TJ4D_VOXEL_SIZE)
    return replace(base, name=f"{base.name}-authors")
