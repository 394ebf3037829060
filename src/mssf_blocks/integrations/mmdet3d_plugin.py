"""mmdetection3d plugin: registers the MSSF middle encoder with mmdet3d's ``MODELS`` registry.

Import it from a config (mmengine runs ``custom_imports`` before building anything)::

    custom_imports = dict(imports=["mssf_blocks.integrations.mmdet3d_plugin"], allow_failed_imports=False)
    model = dict(
        type="MVXFasterRCNN",  # an MVX detector; docs/frameworks.md: the one call it changes
        pts_middle_encoder=dict(
            type="MSSFSparseEncoder", in_channels=7, sparse_shape=[41, 1024, 1024],
            point_cloud_range=[0, -25.6, -3, 51.2, 25.6, 2], voxel_size=[0.05, 0.05, 0.125],
            num_fusion_blocks=2, image_channels=[256, 256, 256, 256]),
        ...)

Importing this module imports ``mmdet3d.registry`` (to register) and registers :class:`MSSFSparseEncoder`
and :class:`~mssf_blocks.integrations.mmdet3d_pillars.MSSFPillarEncoder`; without mmdet3d it does nothing
(:func:`register_mmdet3d_modules` returns whether it registered). The detector that calls them with the
camera inputs, ``MSSFDetector``, is registered by ``mssf_examples.mmdet3d.plugin``. The encoders are plain ``nn.Module`` s
and need neither mmdet3d nor mmengine.
"""

from __future__ import annotations

from typing import Any, List, Mapping, Optional, Sequence, Tuple, Union

from torch import Tensor, nn

from mssf_blocks.checks.agreement import check_agreement
from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations import _backbones
from mssf_blocks.integrations.mmdet3d import fusion_inputs_from_mmdet3d
from mssf_blocks.integrations.mmdet3d_pillars import MSSFPillarEncoder

__all__ = ["MSSFSparseEncoder", "MSSFPillarEncoder", "register_mmdet3d_modules", "MMDET3D_MODULES"]


# the ``layout`` of the MSSF authors' encoder (their MSSF-V), the word of ``MSSFPillarEncoder`` for their MSSF-PP
_AUTHORS = "authors"
_VOXELNEXT = "VoxelResBackBone8xVoxelNeXt"  # the only layout of theirs that is sparse: their MSSF-V's stages


def _resolve_layout(layout: str, authors_layout: Optional[bool]) -> Tuple[str, bool]:
    """``(layout of the example backbone, whether it is the authors' encoder)`` from the two spellings."""
    if layout == _AUTHORS:
        if authors_layout is not None and not authors_layout:
            raise MSSFError(f"authors_layout: expected True or unset with layout={_AUTHORS!r} (the same switch), "
                            f"got {authors_layout!r}")
        return _VOXELNEXT, True
    if layout not in _backbones.LAYOUTS:
        raise MSSFError(f"layout: expected one of {sorted(_backbones.LAYOUTS) + [_AUTHORS]}, got {layout!r}")
    if authors_layout and layout != _VOXELNEXT:
        raise MSSFError(f"authors_layout: True means layout={_AUTHORS!r} (the authors' VoxelNeXt encoder); expected "
                        f"layout={_AUTHORS!r} or {_VOXELNEXT!r} with it, got layout={layout!r}")
    return layout, bool(authors_layout)


class MSSFSparseEncoder(nn.Module):
    """mmdet3d middle encoder (``SparseEncoder`` contract) running an MSSF fusion backbone.

    ``forward(voxel_features (N, C), coors (N, 4) (batch, z, y, x), batch_size, points=None,
    img_features=None, batch_input_metas=None)`` returns the dense BEV ``(B, C_out * D, H, W)`` of
    ``conv_out`` (as ``SparseEncoder``; with ``return_middle_feats`` also the four stage spconv tensors).
    The camera keyword arguments are those the authors' MSSF detectors pass to their middle encoder:
    ``points`` (per-sample ``(P_i, 3 + C)``), ``img_features`` (``extract_img_feat``'s levels) and
    ``batch_input_metas`` (``[s.metainfo for s in batch_data_samples]``); they are needed only when
    ``num_fusion_blocks > 0``.

    Args:
        in_channels: voxel feature channels.
        sparse_shape: ``(D + 1, H, W)`` as in ``SparseEncoder`` configs (checked against the grid).
        point_cloud_range, voxel_size: the data preprocessor's ``voxel_layer`` values.
        layout: ``"VoxelBackBone8x"`` (SECOND; mmdet3d's default ``SparseEncoder``),
            ``"VoxelResBackBone8x"`` (CenterPoint's residual layout) or ``"VoxelResBackBone8xVoxelNeXt"``
            (MSSF-V: OpenPCDet's VoxelNeXt layout, six residual stages, stages 4-6 merged into a sparse BEV at
            stride 8, ``conv_out`` and ``shared_conv``; ``forward`` then returns ``[SparseConvTensor]``, the sparse
            BEV with 2-d indices ``(b, y, x)``, for a sparse head such as ``MSSFVoxelNeXtHead``, without
            ``pts_backbone`` / ``pts_neck``; ``sparse_shape`` pads z by one cell as the others), or ``"authors"``:
            the MSSF authors' MSSF-V encoder, ``SparseEncoderVoxelNeXtFuse`` (the VoxelNeXt stages with their
            fusion modules' forward, a regular ``conv_out``, a biased ``shared_conv``), into which their released
            checkpoint loads (``mssf_examples.mmdet3d.authors_mssf_v``); the same word as
            ``MSSFPillarEncoder(layout="authors")`` for their MSSF-PP.
        num_fusion_blocks, fusion, fusion_position, image_channels, msdff_heads, msdff_points,
        msdff_value_projection, msdff_value_dim, seg_hidden, channels, out_channels: as the example backbones
            (``mssf_examples.models.backbones.SparseFusionBackbone``); ``seg_hidden=None`` means no semantic head.
        image_aug: ``"meta"`` or ``"none"``, see :func:`~mssf_blocks.integrations.mmdet3d.camera_from_meta`.
        authors_layout: the older spelling of ``layout="authors"``, kept for existing configs: ``True`` with
            ``layout="VoxelResBackBone8xVoxelNeXt"`` (or ``"authors"``) builds the same module, with the same
            state-dict keys; ``True`` with another layout, or ``False`` with ``"authors"``, is refused.
            ``None`` / ``False`` otherwise: the layout as named (OpenPCDet's VoxelNeXt tail for the VoxelNeXt one).
        return_middle_feats: also return the stage outputs (as ``SparseEncoder``).

    Attributes:
        layout: the layout built, ``"authors"`` for either spelling of the authors' encoder.
        authors_layout: whether it is the authors' encoder (``True`` for either spelling).
    """

    def __init__(
        self,
        in_channels: int,
        sparse_shape: Sequence[int],
        point_cloud_range: Sequence[float],
        voxel_size: Sequence[float],
        layout: str = "VoxelBackBone8x",
        num_fusion_blocks: int = 1,
        fusion: str = "msdff",
        fusion_position: str = "before_residual",
        image_channels: Optional[Sequence[int]] = None,
        msdff_heads: int = 8,
        msdff_points: int = 4,
        msdff_value_projection: Optional[str] = None,
        msdff_value_dim: Union[int, str, None] = None,
        seg_hidden: Optional[Sequence[int]] = None,
        channels: Optional[Sequence[int]] = None,
        out_channels: Optional[int] = None,
        image_aug: str = "meta",
        authors_layout: Optional[bool] = None,
        return_middle_feats: bool = False,
    ) -> None:
        super().__init__()
        net_layout, authors = _resolve_layout(layout, authors_layout)
        self.net = _backbones.build(
            net_layout, in_channels, point_cloud_range, voxel_size, num_fusion_blocks=num_fusion_blocks, fusion=fusion,
            fusion_position=fusion_position, image_channels=image_channels, msdff_heads=msdff_heads,
            msdff_points=msdff_points, msdff_value_projection=msdff_value_projection,
            msdff_value_dim=msdff_value_dim, seg_hidden=seg_hidden,
            channels=channels, out_channels=out_channels, authors_layout=authors,
            **self._layout_kwargs(net_layout),
        )
        self.layout = _AUTHORS if authors else net_layout
        self.sparse_bev = net_layout == _VOXELNEXT
        self.authors_layout = authors
        if self.sparse_bev and not self.authors_layout:
            _backbones.openpcdet_voxelnext_tail(self.net)
        if [int(s) for s in sparse_shape] != list(self.net.input_shape):
            raise MSSFError(
                f"sparse_shape: expected {list(self.net.input_shape)} (z + 1, y, x of point_cloud_range / voxel_size), "
                f"got {list(sparse_shape)}"
            )
        self.sparse_shape = list(self.net.input_shape)
        self.in_channels = int(in_channels)
        self.image_channels = None if image_channels is None else [int(c) for c in image_channels]
        self.image_aug = image_aug
        self.return_middle_feats = bool(return_middle_feats)
        self.last_output = None  # the backbone output of the latest forward (for seg_loss)

    @staticmethod
    def _layout_kwargs(layout: str) -> dict:
        # VoxelNeXt's grid is padded by one z cell as SparseEncoder's (sparse_shape z + 1); the dense layouts pad
        # by default
        return {"z_pad": 1} if layout == _VOXELNEXT else {}

    @property
    def num_fusion_blocks(self) -> int:
        return self.net.num_fusion_blocks

    def forward(
        self,
        voxel_features: Tensor,
        coors: Tensor,
        batch_size: Union[int, Tensor],
        points: Optional[Sequence[Tensor]] = None,
        img_features: Optional[Sequence[Tensor]] = None,
        batch_input_metas: Optional[Sequence[Mapping]] = None,
        **kwargs: Any,
    ) -> Union[Tensor, Tuple[Tensor, List[Any]]]:
        inputs = None
        batch_size = int(batch_size)  # (read once: a 0-d tensor from VoxelNet.extract_feat)
        if self.num_fusion_blocks:
            missing = [n for n, v in (("points", points), ("img_features", img_features),
                                      ("batch_input_metas", batch_input_metas)) if v is None]
            if missing:
                raise MSSFError(
                    f"{', '.join(missing)}: required by the fusion blocks; pass points=..., img_features=..., "
                    "batch_input_metas=... to the middle encoder (docs/frameworks.md)"
                )
            # the voxels' batch_size (from coors) decides which per-sample list is short
            check_agreement([(n, len(v), f"(a list of {len(v)})") for n, v in (("points", points),
                             ("batch_input_metas", batch_input_metas)) if isinstance(v, (list, tuple))],
                            "number of samples", ("batch_size", batch_size))
            inputs = fusion_inputs_from_mmdet3d(points, img_features, batch_input_metas, image_aug=self.image_aug)
        if self.sparse_bev:
            out, encoded = _backbones.run_voxelnext_layout(self.net, voxel_features, coors, batch_size, inputs)
            self.last_output = out if out.seg_logits is not None else None
            return [encoded]
        out, encoded = _backbones.run_dense_layout(self.net, voxel_features, coors, batch_size, inputs)
        self.last_output = out if out.seg_logits is not None else None
        from mssf_blocks.integrations.spconv import dense

        bev = dense(encoded).flatten(1, 2)  # (B, C, D, H, W) -> (B, C * D, H, W), as SparseEncoder
        if self.return_middle_feats:
            return bev, list(_backbones.stage_spconv(out).values())
        return bev

    def seg_loss(self, points: Sequence[Tensor], gt_bboxes_3d: Sequence[Any]) -> Tensor:
        """The semantic head's focal loss for the latest forward.

        Args:
            points: the per-sample points given to ``forward``.
            gt_bboxes_3d: per sample ``LiDARInstance3DBoxes`` (their ``.tensor``) or ``(G, 7+)`` tensors,
                mmdet3d's bottom-centre boxes.
        """
        if self.last_output is None:
            raise MSSFError("seg_loss: no semantic-head output; build with seg_hidden and num_fusion_blocks > 0, then run forward")
        from mssf_blocks.integrations._common import mmdet3d_seg_loss

        return mmdet3d_seg_loss(self.net.seg_head, self.last_output, points, gt_bboxes_3d)


#: name -> class, registered by :func:`register_mmdet3d_modules`
MMDET3D_MODULES = {"MSSFSparseEncoder": MSSFSparseEncoder, "MSSFPillarEncoder": MSSFPillarEncoder}


def register_mmdet3d_modules(registry: Any = None) -> bool:
    """Register :data:`MMDET3D_MODULES` with ``registry`` (default ``mmdet3d.registry.MODELS``).

    Idempotent (a name already bound to the same class is skipped). Returns ``False`` without a
    registry and without mmdet3d; raises :class:`MSSFError` if a name is taken by another class.
    """
    if registry is None:
        try:
            from mmdet3d.registry import MODELS as registry
        except ImportError:
            return False
    for name, cls in MMDET3D_MODULES.items():
        existing = registry.module_dict.get(name)
        if existing is cls:
            continue
        if existing is not None:
            raise MSSFError(f"registry: {name!r} is already registered to {existing!r}")
        registry.register_module(name=name, module=cls)
    return True


REGISTERED = register_mmdet3d_modules()
