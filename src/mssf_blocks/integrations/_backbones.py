"""The example fusion backbones (SECOND / CenterPoint layouts) behind both frameworks' contracts.

The sparse layers live in ``mssf_examples.models.backbones`` (spconv); this module builds them from a
framework's grid description and runs them up to the layers a framework's neck expects (the
``conv_out`` spconv tensor). ``mssf_examples`` and spconv are imported when a backbone is built,
never at import time.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.sparse_voxels import SparseVoxels

__all__: list = []

#: framework layout name -> example backbone class
LAYOUTS = {"VoxelBackBone8x": "SECONDBackbone", "VoxelResBackBone8x": "CenterPointBackbone",
           "VoxelResBackBone8xVoxelNeXt": "VoxelNeXtBackbone"}
FUSION_KWARGS = ("num_fusion_blocks", "fusion", "fusion_position", "image_channels", "msdff_heads",
                 "msdff_points", "msdff_value_projection", "msdff_value_dim", "seg_hidden", "channels", "out_channels")


def _examples_backbones() -> Any:
    try:
        from mssf_examples.models import backbones
    except ImportError as exc:
        raise ImportError(
            "the framework backbones are built from mssf_examples.models.backbones (spconv): install the examples "
            "package and spconv (see README, 'examples') to use them; the input adapters need neither"
        ) from exc
    return backbones


def build(layout: str, in_channels: int, point_cloud_range: Sequence[float], voxel_size: Sequence[float],
          grid_size: Optional[Sequence[int]] = None, **kwargs: Any) -> Any:
    """An example backbone of ``layout`` (``"VoxelBackBone8x"`` / ``"VoxelResBackBone8x"``).

    ``grid_size`` ``(nx, ny, nz)`` (what the framework computed) must match the grid of
    ``point_cloud_range`` / ``voxel_size``.
    """
    if layout not in LAYOUTS:
        raise MSSFError(f"layout: expected one of {sorted(LAYOUTS)}, got {layout!r}")
    layout_kwargs = {"z_pad": int(kwargs.pop("z_pad"))} if "z_pad" in kwargs else {}  # the framework's, not a setting
    if kwargs.pop("authors_layout", False):  # the MSSF authors' VoxelNeXt (their checkpoints), VoxelNeXt only
        if layout != "VoxelResBackBone8xVoxelNeXt":
            raise MSSFError("authors_layout: the authors' layout exists for 'VoxelResBackBone8xVoxelNeXt', "
                            f"got layout={layout!r}")
        layout_kwargs["authors_layout"] = True
    unknown = sorted(set(kwargs) - set(FUSION_KWARGS))
    if unknown:
        raise MSSFError(f"backbone settings: unknown {unknown}; expected among {FUSION_KWARGS}")
    kwargs = {k: v for k, v in kwargs.items() if v is not None or k == "seg_hidden"}
    if kwargs.get("seg_hidden", None) is not None:
        kwargs["seg_hidden"] = tuple(int(c) for c in kwargs["seg_hidden"])
    if "image_channels" in kwargs:
        kwargs["image_channels"] = [int(c) for c in kwargs["image_channels"]]
    kwargs.setdefault("seg_hidden", None)
    bb = _examples_backbones()
    from mssf_blocks.voxel_grid import VoxelGrid

    grid = VoxelGrid(voxel_size=tuple(float(v) for v in voxel_size),
                     point_cloud_range=tuple(float(v) for v in point_cloud_range))
    if grid_size is not None:
        given = tuple(int(g) for g in (grid_size.tolist() if hasattr(grid_size, "tolist") else grid_size))
        if given != grid.grid_size:
            raise MSSFError(
                f"grid_size: expected {grid.grid_size} (point_cloud_range / voxel_size), got {given}"
            )
    return getattr(bb, LAYOUTS[layout])(int(in_channels), grid, **kwargs, **layout_kwargs)


def _input_voxels(net: Any, voxel_features: Tensor, voxel_coords: Tensor, batch_size: int) -> Any:
    if not isinstance(voxel_coords, Tensor) or voxel_coords.dim() != 2 or voxel_coords.shape[1] != 4:
        raise MSSFError(f"voxel_coords: expected (N, 4) (batch, z, y, x), got {getattr(voxel_coords, 'shape', voxel_coords)!r}")
    coords = voxel_coords.to(torch.int32)
    if not torch.equal(coords.to(voxel_coords.dtype), voxel_coords):
        raise MSSFError("voxel_coords: expected integer voxel indices")
    from mssf_blocks.integrations.spconv import enable_cpu_backward

    enable_cpu_backward()  # spconv's backward on a CPU-only torch (no effect on CUDA builds)
    return SparseVoxels(voxel_features, coords, batch_size=int(batch_size), grid=net.grid)


def run_dense_layout(net: Any, voxel_features: Tensor, voxel_coords: Tensor, batch_size: int,
                     fusion_inputs: Any) -> Tuple[Any, Any]:
    """``(BackboneOutput, conv_out spconv tensor)`` of a SECOND/CenterPoint example backbone."""
    from mssf_blocks.integrations.spconv import quiet

    voxels = _input_voxels(net, voxel_features, voxel_coords, batch_size)
    out = net.forward_stages(voxels, fusion_inputs)
    with quiet():  # spconv's own torch.fx / indexing messages (see mssf_blocks.integrations.spconv)
        return out, net.conv_out(out.stages[-1].to_spconv())


def run_voxelnext_layout(net: Any, voxel_features: Tensor, voxel_coords: Tensor, batch_size: int,
                         fusion_inputs: Any) -> Tuple[Any, Any]:
    """``(BackboneOutput, sparse BEV spconv tensor)`` of the example VoxelNeXt backbone: 2D indices
    ``(b, y, x)`` at stride 8 on the ``bev_shape`` grid, as OpenPCDet's ``VoxelResBackBone8xVoxelNeXt``."""
    import spconv.pytorch as spconv

    voxels = _input_voxels(net, voxel_features, voxel_coords, batch_size)
    out = net(voxels, fusion_inputs)
    # the backbone's forward already ran conv_out and shared_conv (once, as OpenPCDet's and the authors' encoders)
    features, indices = out.sparse_bev
    return out, spconv.SparseConvTensor(features, indices.int(), list(net.bev_shape), int(batch_size))


def openpcdet_voxelnext_tail(net: Any) -> None:
    """Give the example VoxelNeXt backbone OpenPCDet's ``VoxelResBackBone8xVoxelNeXt`` tail (both frameworks' MSSF-V):
    a (non-submanifold) 3 x 3 ``SparseConv2d`` over the merged BEV as ``conv_out``, then a 3 x 3 submanifold
    ``shared_conv``. OpenPCDet's shared_conv has a bias before its BatchNorm, which the normalisation cancels; it
    is left out because spconv's CPU kernels refuse biased convolutions in eval mode."""
    import spconv.pytorch as spconv
    from torch import nn

    c, out = net.channels[3], list(net.conv_out)[0].out_channels
    net.conv_out = spconv.SparseSequential(
        spconv.SparseConv2d(c, out, 3, stride=1, padding=1, bias=False, indice_key="spconv_down2"),
        nn.BatchNorm1d(out, eps=1e-3, momentum=0.01), nn.ReLU(),
    )
    net.shared_conv = spconv.SparseSequential(
        spconv.SubMConv2d(out, out, 3, stride=1, padding=1, bias=False), nn.BatchNorm1d(out), nn.ReLU(True),
    )


def stage_spconv(out: Any) -> Dict[str, Any]:
    """``{'x_conv1': ..., 'x_conv4': ...}`` spconv tensors of the four stages (index caches kept)."""
    return {f"x_conv{i + 1}": s.to_spconv() for i, s in enumerate(out.stages[:4])}


def seg_loss(net: Any, out: Any, points: Tensor, points_batch: Tensor, gt_boxes: Sequence[Tensor]) -> Tensor:
    """Semantic-head focal loss on the centroids of the last fusion block's voxels (augmented frame)."""
    from mssf_blocks.functional.geometry import voxel_centroids

    v: SparseVoxels = out.seg_voxels
    centroids, _ = voxel_centroids(points[:, :3], points_batch, v.coords, v.spatial_shape, v.batch_size,
                                   v.voxel_size, v.point_range_min, v.stride)
    return net.seg_head.loss_from_boxes(out.seg_logits, centroids.to(out.seg_logits.dtype), v.batch_index,
                                        [g.to(centroids) for g in gt_boxes])
