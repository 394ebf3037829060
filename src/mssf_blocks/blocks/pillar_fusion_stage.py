"""``PillarFusionStage``: one MSSF fusion step on a BEV map (lift, fuse, head, back to BEV).

Paper Sec. III-G ("Extend to Pillar"): the BEV map is lifted into the non-empty voxels of the radar
points (:class:`~mssf_blocks.lift.PillarLift`), fused with the image (:class:`~mssf_blocks.blocks.FusionBlock`,
with its semantic head when it is the last one) and summed back per ``(x, y)``. The paper's text leaves
the merge with the existing map open; the authors' MSSF-PP (``PointPillarsScatterFuse`` and
``SECONDFuse`` of ``EricLiuhhh/MSSF``) concatenates the summed map with the map it started from, and
adds the voxel's BEV feature to the MSDFF query. Both are switches here:

* ``merge="replace"``: pillars holding voxels get the sum of their fused voxels, the others keep the
  map (the channels stay ``C``); ``merge="concat"``: ``cat([bev, sum], 1)`` with zeros where no voxel
  is (``2 C`` channels, the authors');
* ``bev_in_query=True``: the MSDFF query is ``QueryInit(.) + BEV(x, y)`` (the authors').

The authors' raw-voxel term (``conv_input``) is :class:`PillarLift`'s ``raw_channels``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from mssf_blocks.blocks.fusion_block import FusionBlock
from mssf_blocks.blocks.fusion_block_output import FusionBlockOutput
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.lift import _add_into_pillars, pillar_lift
from mssf_blocks.samplers import FusionInputs
from mssf_blocks.lift.pillar_lift import PillarLift
from mssf_blocks.sparse_voxels import SparseVoxels

__all__ = ["PillarFusionStage"]

_MERGES = ("replace", "concat")


class PillarFusionStage(nn.Module):
    """Lift a BEV map into voxels, fuse them with the image, merge the result back into the map.

    Args:
        lift: the :class:`PillarLift` (``channels`` = the map's ``C``).
        block: a :class:`FusionBlock` without ``downsample`` / ``blocks`` (a BEV stage has no sparse
            convolutions), with its ``semantic_head`` when this is the last fusion stage.
        merge: ``"replace"`` (default) or ``"concat"`` (the authors' MSSF-PP), see the module doc.
        bev_in_query: add ``BEV(x, y)`` to the MSDFF query (the authors' ``SECONDFuse``).

    ``forward(bev, voxels, inputs, return_logits=False)``: ``bev (B, C, H_b, W_b)``, ``voxels`` the
    lift voxels (their features are read only by ``lift.raw_conv``); returns the merged map
    ``(B, C or 2 C, H_b, W_b)``, or a :class:`~mssf_blocks.FusionBlockOutput` ``(map, head_voxels, logits)`` (with the head voxels' ``.centroids``) with ``return_logits=True``.
    """

    def __init__(self, lift: PillarLift, block: FusionBlock, merge: str = "replace", bev_in_query: bool = False) -> None:
        super().__init__()
        if not isinstance(lift, PillarLift):
            raise MSSFError(f"lift: expected a PillarLift, got {type(lift).__name__}")
        if not isinstance(block, FusionBlock):
            raise MSSFError(f"block: expected a FusionBlock, got {type(block).__name__}")
        if block.downsample is not None or block.blocks is not None:
            raise MSSFError("block: expected a FusionBlock without downsample and blocks (a BEV stage has no sparse convs)")
        if block.out_channels != lift.channels:
            raise MSSFError(f"block: expected {lift.channels} channels (lift.channels), got {block.out_channels}")
        if merge not in _MERGES:
            raise MSSFError(f"merge: expected one of {_MERGES}, got {merge!r}")
        if not isinstance(bev_in_query, bool):
            raise MSSFError(f"bev_in_query: expected a bool, got {bev_in_query!r}")
        self.lift, self.block, self.merge, self.bev_in_query = lift, block, merge, bev_in_query

    @property
    def out_channels(self) -> int:
        return self.lift.channels * (2 if self.merge == "concat" else 1)

    def forward(self, bev: Tensor, voxels: SparseVoxels, inputs: FusionInputs, return_logits: bool = False) -> Any:
        lifted = self.lift(bev, voxels)
        query_add = pillar_lift(bev, voxels.coords, None, self.lift.stride) if self.bev_in_query else None
        out = self.block(lifted, inputs, return_logits=return_logits, query_add=query_add)
        fused = out[0] if return_logits else out
        f = fused.features
        if self.merge == "concat":
            merged = torch.cat([bev.to(f.dtype), self.lift.to_bev(fused)], 1)
        else:
            sy, sx = self.lift.stride
            c = fused.coords.long()
            wb = bev.shape[-1]
            cell = torch.div(c[:, 2], sy, rounding_mode="floor") * wb + torch.div(c[:, 3], sx, rounding_mode="floor")
            merged = _add_into_pillars(bev.to(f.dtype).clone(), c[:, 0], cell, f, clear=True)
        if return_logits:
            return FusionBlockOutput(merged, out.head_voxels, out.logits, out.centroids, out.has_points)
        return merged

    def extra_repr(self) -> str:
        return f"merge={self.merge!r}, bev_in_query={self.bev_in_query}"
