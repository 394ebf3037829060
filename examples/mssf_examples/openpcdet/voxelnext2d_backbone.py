"""VoxelNeXt-2D (the pillar VoxelNeXt of the paper's plug-and-play table) with MSSF fusion, for OpenPCDet
(``BACKBONE_3D.NAME: MSSFVoxelResBackBone8xVoxelNeXt2D``).

OpenPCDet's ``VoxelResBackBone8xVoxelNeXt2D`` (its ``voxelnext2d_ioubranch.yaml``: ``DynamicPillarVFESimple2D``
-> this backbone -> ``VoxelNeXtHead``) runs six stages of 2D sparse convolutions on the pillars: ``conv1`` (three
residual blocks, stride 1) and ``conv2..6`` (a strided sparse convolution, then residual blocks). As MSSF-PP
(paper Sec. III, "Extend to Pillar"), stage ``i < NUM_FUSION_BLOCKS`` fuses after its strided convolution
(``FUSION_POSITION: before_residual``; ``conv1`` has none: before its blocks) or after the whole stage
(``after_residual``): its sparse pillar map is made dense, lifted into the radar points' voxels, fused and
summed back (:class:`~mssf_examples.openpcdet.pillar_fusion.PillarFusionStages`), and the active pillars take
their new features (a pillar holding radar points is always active: the strided convolutions keep every cell
whose window covers an active one).

Everything else is OpenPCDet's class (its subclass: the same layers and names), less the biases of the sparse
convolutions, each of which a BatchNorm follows (a per-channel constant it cancels): spconv's CPU kernels
refuse biased convolutions in evaluation mode (``cpu don't support act and bias``), as for
``MSSFVoxelResBackBone8xVoxelNeXt``. Its widths are fixed (32, 64, 128, 256, 256, 256; ``VFE.NUM_FILTERS:
[32]``). Importing this module imports OpenPCDet.
"""

from __future__ import annotations

from typing import Any

import torch
from pcdet.models.backbones_3d.spconv_backbone_voxelnext2d import VoxelResBackBone8xVoxelNeXt2D
from pcdet.utils.spconv_utils import spconv
from spconv.pytorch.conv import SparseConvolution

from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations.openpcdet import fusion_inputs_from_batch_dict

from .pillar_fusion import PillarFusionStages

__all__ = ["OPENPCDET_PILLAR_BACKBONES", "MSSFVoxelResBackBone8xVoxelNeXt2D"]

#: channels and x/y stride of conv1..conv6 (OpenPCDet's, fixed)
STAGE_CHANNELS = (32, 64, 128, 256, 256, 256)
STAGE_STRIDES = (1, 2, 4, 8, 16, 32)


def drop_sparse_conv_biases(module: torch.nn.Module) -> list:
    """Remove the bias of every spconv convolution in ``module`` (each is followed by a BatchNorm); returns
    the names of the removed parameters."""
    dropped = []
    for name, m in module.named_modules():
        if isinstance(m, SparseConvolution) and m.bias is not None:
            m.bias = None
            dropped.append(f"{name}.bias")
    return dropped


class MSSFVoxelResBackBone8xVoxelNeXt2D(PillarFusionStages, VoxelResBackBone8xVoxelNeXt2D):
    """OpenPCDet's ``VoxelResBackBone8xVoxelNeXt2D`` with MSSF fusion in its first ``NUM_FUSION_BLOCKS`` stages.

    ``forward(batch_dict)`` reads ``pillar_features (N, 32)`` / ``pillar_coords (N, 3)`` ``(b, y, x)``
    (``DynamicPillarVFESimple2D``), ``points`` and the camera keys and image levels when it fuses; it writes what
    OpenPCDet's writes (``encoded_spconv_tensor`` at stride 8, ``multi_scale_2d_features``), plus
    ``mssf_seg_logits`` with the semantic head; :meth:`get_loss` gives the head's focal loss.
    """

    def __init__(self, model_cfg: Any, input_channels: int, grid_size: Any, voxel_size: Any = None,
                 point_cloud_range: Any = None, **kwargs: Any) -> None:
        if int(input_channels) != STAGE_CHANNELS[0]:
            raise MSSFError(f"MODEL.VFE.NUM_FILTERS: VoxelResBackBone8xVoxelNeXt2D takes {STAGE_CHANNELS[0]} pillar "
                            f"channels, the VFE gives {input_channels}")
        VoxelResBackBone8xVoxelNeXt2D.__init__(self, model_cfg, input_channels, grid_size)
        drop_sparse_conv_biases(self)
        self.init_fusion(model_cfg, "BACKBONE_3D", ("SPCONV_KERNEL_SIZES",), STAGE_CHANNELS, STAGE_STRIDES,
                         voxel_size, point_cloud_range)

    def _fuse_sparse(self, i: int, x: Any, voxels: Any, inputs: Any, batch_dict: dict[str, Any]) -> Any:
        merged = self.fuse(i, x.dense(), voxels, inputs, batch_dict)
        idx = x.indices.long()
        return x.replace_feature(merged[idx[:, 0], :, idx[:, 1], idx[:, 2]])

    def forward(self, batch_dict: dict[str, Any]) -> dict[str, Any]:
        x = spconv.SparseConvTensor(features=batch_dict["pillar_features"],
                                    indices=batch_dict["pillar_coords"].int(),
                                    spatial_shape=self.sparse_shape, batch_size=batch_dict["batch_size"])
        inputs = lifts = None
        if self.num_fusion_blocks:
            inputs = fusion_inputs_from_batch_dict(batch_dict, **self.adapter_kwargs)
            lifts = self.lift_voxels(batch_dict)
        convs = []
        for i, stage in enumerate((self.conv1, self.conv2, self.conv3, self.conv4, self.conv5, self.conv6)):
            layers = list(stage._modules.values())
            split = len(layers) if self.fusion_position == "after_residual" else (0 if i == 0 else 1)
            for layer in layers[:split]:
                x = layer(x)
            if i < self.num_fusion_blocks:
                x = self._fuse_sparse(i, x, lifts[i], inputs, batch_dict)
            for layer in layers[split:]:
                x = layer(x)
            convs.append(x)
        x_conv1, x_conv2, x_conv3, x_conv4, x_conv5, x_conv6 = convs
        # OpenPCDet's merge of stages 4-6 into one sparse BEV at stride 8 (its forward, unchanged)
        x_conv5.indices[:, 1:] *= 2
        x_conv6.indices[:, 1:] *= 4
        x_conv4 = x_conv4.replace_feature(torch.cat([x_conv4.features, x_conv5.features, x_conv6.features]))
        x_conv4.indices = torch.cat([x_conv4.indices, x_conv5.indices, x_conv6.indices])
        out = self.shared_conv(self.conv_out(self.bev_out(x_conv4)))
        batch_dict.update({
            "encoded_spconv_tensor": out,
            "encoded_spconv_tensor_stride": 8,
            "multi_scale_2d_features": {"x_conv1": x_conv1, "x_conv2": x_conv2, "x_conv3": x_conv3,
                                        "x_conv4": x_conv4, "x_conv5": x_conv5},
            "multi_scale_2d_strides": {"x_conv1": 1, "x_conv2": 2, "x_conv3": 4, "x_conv4": 8, "x_conv5": 16},
        })
        return batch_dict


#: what to merge into ``pcdet.models.backbones_3d.__all__``
OPENPCDET_PILLAR_BACKBONES = {"MSSFVoxelResBackBone8xVoxelNeXt2D": MSSFVoxelResBackBone8xVoxelNeXt2D}
