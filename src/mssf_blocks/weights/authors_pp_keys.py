"""The authors' MSSF-PP fusion stages (``EricLiuhhh/MSSF``) as :class:`~mssf_blocks.blocks.pillar_fusion_stage.PillarFusionStage` s.

Their MSSF-PP (``VoxelNetFuse``, config ``pointpillars_hv_secfpn_8xb6-160e_vod-3d-3class_mm_bb_bevfeat_lr0001``)
fuses twice:

* the middle encoder ``PointPillarsScatterFuse`` (prefix ``middle_encoder``): radar voxels at
  0.16 x 0.16 x 0.125 m (``41 x 320 x 320``), mean point features, ``conv_input`` (``SubMConv3d`` 7 -> 64,
  no bias, no norm), query ``query_proj(cat(img, x, p))``, MSDFF, semantic head, summed per pillar and
  concatenated with the scattered pillar map (64 + 64 channels);
* the BEV backbone ``SECONDFuse`` (prefix ``backbone``), after its whole first block: radar voxels at
  0.32 x 0.32 x 0.125 m (``41 x 160 x 160``), ``conv_input(voxels) + BEV(y, x) + height_embeddings(z)``,
  query ``query_proj(cat(img, x, p)) + BEV(y, x)``, MSDFF, semantic head, summed and concatenated with
  the block's output (64 + 64 channels) before the second block.

:func:`mssf_pp_stage_maps` gives the :class:`~mssf_blocks.weights.ModuleMap` s of one stage;
``OFFICIAL_SWITCHES["pillar_stage" | "pillar_lift"]`` (``SECONDFuse``) and ``["pillar_scatter_stage" |
"pillar_scatter_lift"]`` (``PointPillarsScatterFuse``) configure the modules.
"""

from __future__ import annotations

from typing import List, Tuple

from mssf_blocks.errors import MSSFError
from mssf_blocks.weights.authors_checkpoint import ModuleMap

__all__ = ["mssf_pp_stage_maps"]


def mssf_pp_stage_maps(stage: str, ours: str, voxel_channels: int, fusion: str = "msdff",
                       encoder: str = "") -> Tuple[List[ModuleMap], List[str]]:
    """The tensors of one MSSF-PP fusion stage in their state dict -> our :class:`PillarFusionStage`.

    Args:
        stage: ``"scatter"`` (``PointPillarsScatterFuse``, default prefix ``middle_encoder``) or
            ``"backbone"`` (``SECONDFuse``, default prefix ``backbone``).
        ours: our prefix of the :class:`~mssf_blocks.blocks.pillar_fusion_stage.PillarFusionStage` (``""`` for a bare one).
        voxel_channels: the stage's ``C`` (their ``base_channels``, 64).
        fusion: ``"msdff"`` (their ``fusion_block_type='deform'``) or ``"sff"`` (``'simple'``: no query).
        encoder: their prefix (default from ``stage``).

    Returns:
        ``(maps, ignore)``: ``ignore`` holds their query initialiser's dead ``voxel_fuse.img_transform``
        (and ``query_proj`` with ``"sff"``, which never reads it).
    """
    if stage not in ("scatter", "backbone"):
        raise MSSFError(f"stage: expected 'scatter' or 'backbone', got {stage!r}")
    if fusion not in ("msdff", "sff"):
        raise MSSFError(f"fusion: expected 'msdff' or 'sff', got {fusion!r}")
    enc = encoder or ("middle_encoder" if stage == "scatter" else "backbone")
    p = f"{ours}." if ours else ""
    maps = [
        ModuleMap("conv_input", f"{enc}.conv_input", f"{p}lift.raw_conv"),
        ModuleMap(fusion, f"{enc}.fusion_blocks.x_conv1", f"{p}block.fusion"),
        ModuleMap("semantic_head", f"{enc}.seg_heads.x_conv1", f"{p}block.semantic_head"),
    ]
    if fusion == "msdff":
        maps.append(ModuleMap("query_init", f"{enc}.query_proj", f"{p}block.query_init", voxel_channels))
    if stage == "backbone":
        maps.append(ModuleMap("height_embedding", f"{enc}.height_embeddings", f"{p}lift.height_embedding"))
    ignore = [f"{enc}.voxel_fuse.img_transform"]
    if fusion == "sff":  # built regardless, read only by the MSDFF block
        ignore.append(f"{enc}.query_proj")
    return maps, ignore
