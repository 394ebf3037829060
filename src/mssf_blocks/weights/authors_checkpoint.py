"""The MSSF authors' checkpoints (``EricLiuhhh/MSSF``, an mmdetection3d fork) in this library's modules.

Two parts:

* **key maps**, both directions: :func:`official_to_ours` / :func:`ours_to_official` rename (and, for
  the query initialiser, re-order the columns of) the tensors of the fusion modules; every key must be
  mapped or explicitly ignored, anything else raises an :class:`~mssf_blocks.errors.MSSFError` naming
  the keys. :func:`mssf_v_module_maps` lists the modules of their MSSF-V sparse encoder
  (``pts_middle_encoder``).
* **switches** that make our forward equal theirs (all off by default, the paper's formulation stays the
  default). :data:`OFFICIAL_SWITCHES` holds the keyword arguments per module:

  ==================  =============================================  =====================================
  module              switch                                         what it reproduces
  ==================  =============================================  =====================================
  projector           ``half_pixel=False``                           reference point ``u / W_pad`` (their
                                                                     ``proj_to_img(normalize=True)``)
                                                                     instead of ``(u + 0.5) / W``
  projector           ``inside_image_only=False``                    no in-image test: out-of-image voxels
                                                                     in front of the camera are sampled
                                                                     (zero padding) and get the output
                                                                     layers' bias / BN shift
  MSDFF               ``norm_layer=None``                            no norm after ``output_proj`` (the
                                                                     paper's eq. 10 says ``Linear_BN``)
  MSDFF               ``add_query=True``                             ``dropout(output_proj(.)) + query``:
                                                                     their ``MSDeformableAttention``
                                                                     residual, so the block computes
                                                                     ``f_vox + q + f_img`` (``2 f_vox +
                                                                     f_img`` after the first block; the
                                                                     paper: ``f_vox + f_img``)
  MSDFF               ``output_dropout=0.1``                         their ``nn.Dropout(0.1)`` on the
                                                                     attention output (training only)
  SFF                 ``align_corners=True``,                        ``F.grid_sample(align_corners=True)``
                      ``norm_layer=BatchNorm1d(eps=1e-3,             at ``u / W_pad`` and their
                      momentum=0.01)``                               ``img_transform`` BN
  QueryInit           ``position="centroid"``                        the normalised centroid as ``p``
                                                                     (paper: the voxel position; the
                                                                     library's default: the voxel centre)
  QueryInit           ``align_corners=True``                         level-0 sample as their SFF
  ==================  =============================================  =====================================

  Their query-init column order ``cat(f_img, f_vox, p)`` (the paper writes ``cat(f_vox, f_img, p)``)
  needs no switch: :func:`official_to_ours` permutes the columns of ``query_proj.0.weight``, which is
  exact. ``image_size`` of :class:`~mssf_blocks.samplers.FusionInputs` must be their padded input shape
  (``batch_input_shape``) for the reference points to agree.

MSSF-PP's ``conv_input`` branch, ``query + BEV`` query and concatenated BEV: the ``pillar_*`` switches
with :class:`~mssf_blocks.blocks.pillar_fusion_stage.PillarFusionStage` and :mod:`mssf_blocks.weights.authors_pp_keys`.
Not reproduced (documented in ``docs/differences.md``): their projection of points behind the camera
(no depth test), their dense voxel table.

Example:
    >>> import torch
    >>> from mssf_blocks.samplers import MSDFF
    >>> m = MSDFF(32, 16, num_heads=4, num_levels=2, num_points=2, **OFFICIAL_SWITCHES["msdff"])
    >>> maps = [ModuleMap("msdff", "fusion_blocks.x_conv1", "fusion")]
    >>> theirs = ours_to_official({f"fusion.{k}": v for k, v in m.state_dict().items()}, maps)
    >>> sorted(theirs)[0]
    'fusion_blocks.x_conv1.img_cross_att.deformable_attention.attention_weights.bias'
    >>> ours = official_to_ours(theirs, maps)
    >>> all(torch.equal(ours[f"fusion.{k}"], v) for k, v in m.state_dict().items())
    True
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from typing import Dict, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

__all__ = [
    "KINDS",
    "OFFICIAL_SWITCHES",
    "ModuleMap",
    "mssf_v_module_maps",
    "official_to_ours",
    "load_official",
    "ours_to_official",
]

_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")
_LIN = ("weight", "bias")
_DEFORM = "img_cross_att.deformable_attention"

#: Keyword arguments per module that reproduce the authors' forward (see the module doc).
OFFICIAL_SWITCHES: Dict[str, Dict] = {
    "projector": {"half_pixel": False, "inside_image_only": False},
    "msdff": {"norm_layer": None, "add_query": True, "output_dropout": 0.1},
    "sff": {"align_corners": True, "norm_layer": functools.partial(nn.BatchNorm1d, eps=1e-3, momentum=0.01)},
    "query_init": {"position": "centroid", "align_corners": True},
    # the semantic head reads the fused voxels before the stage's residual blocks (also the default)
    "fusion_block": {"head_position": "after_fusion"},
    # MSSF-PP (mssf_blocks.blocks.pillar_fusion_stage): SECONDFuse's stage lifts conv_input(radar voxels) + BEV +
    # HeightEmb (add raw_channels=C_point), adds BEV to the query and concatenates; the middle
    # encoder PointPillarsScatterFuse's stage has no BEV term at all and concatenates
    "pillar_lift": {"use_bev": True, "use_height_embedding": True},
    "pillar_stage": {"merge": "concat", "bev_in_query": True},
    "pillar_scatter_lift": {"use_bev": False, "use_height_embedding": False},
    "pillar_scatter_stage": {"merge": "concat", "bev_in_query": False},
}

#: The module kinds a :class:`ModuleMap` can describe.
KINDS = ("msdff", "sff", "query_init", "semantic_head", "height_embedding", "conv_input")


@dataclass(frozen=True)
class ModuleMap:
    """One module's place in both state dicts.

    Attributes:
        kind: one of :data:`KINDS`: ``"msdff"`` (their ``VoxelFusionBlock``: ``<theirs>.img_cross_att.
            deformable_attention.{sampling_offsets, attention_weights, value_proj, output_proj}`` ->
            our :class:`~mssf_blocks.samplers.MSDFF`, same names), ``"sff"`` (``SimpleVoxelFusionBlock``:
            ``img_transform.0`` / ``.1`` -> ``SFF.linear`` / ``.norm``), ``"query_init"``
            (``query_proj.0`` / ``.1`` -> ``QueryInit.linear`` / ``.norm``, columns permuted),
            ``"semantic_head"`` (``ForegroundSegmentationHead``: ``seg_cls_layer.<i>`` -> our
            ``SemanticGuidedHead.mlp.<i>``, its last Linear -> ``classifier``), ``"height_embedding"``
            (MSSF-PP's ``nn.Embedding`` ``height_embeddings.weight`` -> ``HeightEmbedding.weight``),
            ``"conv_input"`` (MSSF-PP's raw-voxel ``SubMConv3d``, ``conv_input.0.weight`` ->
            ``PillarLift.raw_conv.weight``; give ``ours`` as ``<lift>.raw_conv``).
        theirs: the module's prefix in their state dict (e.g. ``"pts_middle_encoder.query_proj"``).
        ours: the module's prefix in ours (``""`` for a bare module's own state dict).
        voxel_channels: ``"query_init"`` only: ``C_vox``, to split their ``[f_img | f_vox | p]`` columns.
    """

    kind: str
    theirs: str
    ours: str
    voxel_channels: Optional[int] = None

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise MSSFError(f"kind: expected one of {KINDS}, got {self.kind!r}")
        if self.kind == "query_init" and (isinstance(self.voxel_channels, bool) or not isinstance(
                self.voxel_channels, int) or self.voxel_channels < 1):
            raise MSSFError(f"voxel_channels: a 'query_init' map needs a positive int, got {self.voxel_channels!r}")

    def rules(self, theirs_keys: Sequence[str] = ()) -> List[Tuple[str, str]]:
        """``(their suffix, our suffix)`` pairs of this module's tensors."""
        if self.kind == "msdff":
            return [(f"{_DEFORM}.{lin}.{t}", f"{lin}.{t}")
                    for lin in ("sampling_offsets", "attention_weights", "value_proj", "output_proj") for t in _LIN]
        if self.kind in ("sff", "query_init"):
            first = "img_transform." if self.kind == "sff" else ""
            return [(f"{first}0.{t}", f"linear.{t}") for t in _LIN] + [(f"{first}1.{t}", f"norm.{t}") for t in _BN]
        if self.kind == "height_embedding":
            return [("weight", "weight")]
        if self.kind == "conv_input":
            return [("0.weight", "weight")]
        # semantic head: Linear (no bias), BN, ReLU per hidden layer, then the classifier Linear (bias).
        pattern = re.compile(r"seg_cls_layer\.(\d+)\.")
        last = max((int(m.group(1)) for k in theirs_keys for m in [pattern.match(k)] if m), default=None)
        pairs: List[Tuple[str, str]] = []
        if last is None:
            return pairs
        for i in range(0, last, 3):
            pairs += [(f"seg_cls_layer.{i}.weight", f"mlp.{i}.weight")]
            pairs += [(f"seg_cls_layer.{i + 1}.{t}", f"mlp.{i + 1}.{t}") for t in _BN]
        return pairs + [(f"seg_cls_layer.{last}.{t}", f"classifier.{t}") for t in _LIN]


def _join(prefix: str, suffix: str) -> str:
    return f"{prefix}.{suffix}" if prefix else suffix


def _under(key: str, prefix: str) -> bool:
    return not prefix or key.startswith(prefix + ".")


def _permute_query_columns(weight: Tensor, voxel_channels: int, to_ours: bool, key: str) -> Tensor:
    """``[f_img | f_vox | p]`` (theirs) <-> ``[f_vox | f_img | p]`` (ours) columns of ``(C_out, C_in)``."""
    c_in = weight.shape[1] if weight.dim() == 2 else -1
    c_img = c_in - voxel_channels - 3
    if c_img < 1:
        raise MSSFError(f"{key}: expected a (C_out, C_img + {voxel_channels} + 3) query-init weight "
                        f"(voxel_channels={voxel_channels}), got shape {tuple(weight.shape)}")
    first, second = (c_img, voxel_channels) if to_ours else (voxel_channels, c_img)
    return torch.cat([weight[:, first:first + second], weight[:, :first], weight[:, first + second:]], 1)


def _convert(state_dict: Mapping[str, Tensor], maps: Sequence[ModuleMap], ignore: Sequence[str],
             to_ours: bool, strict: bool = True) -> Dict[str, Tensor]:
    if not all(isinstance(m, ModuleMap) for m in maps):
        raise MSSFError(f"maps: expected a sequence of ModuleMap, got {[type(m).__name__ for m in maps]}")
    src_of = (lambda m: m.theirs) if to_ours else (lambda m: m.ours)
    keys = list(state_dict)
    out: Dict[str, Tensor] = {}
    claimed = set()
    absent: List[str] = []
    for m in maps:
        mine = [k for k in keys if _under(k, src_of(m))]
        suffixes = [k[len(src_of(m)) + 1:] if src_of(m) else k for k in mine]
        their_suffixes = suffixes if to_ours else []
        rules = m.rules(their_suffixes)
        if m.kind == "semantic_head" and not to_ours:
            # our side: rebuild their numbering from ours (mlp.<i> keeps i; classifier -> the next index)
            idx = [int(x.group(1)) for s in suffixes for x in [re.match(r"mlp\.(\d+)\.", s)] if x]
            last = (max(idx) // 3 + 1) * 3 if idx else 0
            rules = m.rules([f"seg_cls_layer.{last}.weight"])
        for theirs_sfx, ours_sfx in rules:
            src_sfx, dst_sfx = (theirs_sfx, ours_sfx) if to_ours else (ours_sfx, theirs_sfx)
            src = _join(src_of(m), src_sfx)
            if src not in state_dict:
                # a BN counter may be untracked; anything else a mapped module has must be there
                if not src.endswith("num_batches_tracked") and not any(src == p or _under(src, p) for p in ignore):
                    absent.append(src)
                continue
            dst = _join(m.ours if to_ours else m.theirs, dst_sfx)
            value = state_dict[src]
            if m.kind == "query_init" and src_sfx.endswith("weight") and not src_sfx.startswith(("1.", "norm.")):
                value = _permute_query_columns(value, m.voxel_channels, to_ours, src)
            out[dst] = value
            claimed.add(src)
    if absent and strict:
        side = "their (official)" if to_ours else "our"
        shown = ", ".join(absent[:12]) + (f", ... ({len(absent)} in all)" if len(absent) > 12 else "")
        raise MSSFError(
            f"state_dict: {len(absent)} tensor(s) of a mapped module missing from the {side} state dict: "
            f"{shown}. Loading would keep the module's initial values; pass their prefix in ignore=(...) "
            "to skip them on purpose (or strict=False)"
        )
    left = [k for k in keys if k not in claimed and not any(_under(k, p) for p in ignore)]
    if left:
        side = "their (official)" if to_ours else "our"
        shown = ", ".join(left[:12]) + (f", ... ({len(left)} in all)" if len(left) > 12 else "")
        raise MSSFError(
            f"state_dict: {len(left)} key(s) of the {side} state dict map to no module: {shown}. Add a "
            "ModuleMap for the module they belong to, or pass their prefix in ignore=(...) to leave them out"
        )
    return out


def official_to_ours(state_dict: Mapping[str, Tensor], maps: Sequence[ModuleMap],
                     ignore: Sequence[str] = (), strict: bool = True) -> Dict[str, Tensor]:
    """Their state dict -> ours: the tensors of every mapped module under our names.

    Args:
        state_dict: their (full or partial) state dict.
        maps: the modules to convert (:func:`mssf_v_module_maps` for MSSF-V).
        ignore: prefixes of their keys to leave out (the rest of the detector, dead parameters), or
            whose absence is allowed.
        strict: ``True`` (default): a tensor of a mapped module that is missing from ``state_dict``
            (other than a BN's ``num_batches_tracked``) and not under an ``ignore`` prefix is an error.

    Returns:
        A new dict of our keys (values shared, except the permuted query-init weight). Load it with
        :func:`load_official` (which also checks every key and shape against the module before copying
        anything), or ``model.load_state_dict(...)`` next to the weights of the rest of the model.

    Raises:
        MSSFError: naming every key that no map claims and no ``ignore`` prefix covers (a key under a
            mapped module that fits none of its tensors, e.g. a ``lateral_conv``, included), and with
            ``strict`` every missing tensor of a mapped module.
    """
    return _convert(state_dict, maps, ignore, to_ours=True, strict=strict)


def ours_to_official(state_dict: Mapping[str, Tensor], maps: Sequence[ModuleMap],
                     ignore: Sequence[str] = (), strict: bool = True) -> Dict[str, Tensor]:
    """Our state dict -> theirs (the inverse of :func:`official_to_ours`; ``ignore`` holds our prefixes).

    Raises:
        MSSFError: naming every key of ours that no map claims (e.g. ``norm.*`` of an MSDFF built with a
            norm, which their module does not have) and no ``ignore`` prefix covers.
    """
    return _convert(state_dict, maps, ignore, to_ours=False, strict=strict)


def mssf_v_module_maps(
    fusion_blocks: Mapping[str, str],
    query_init: Optional[str] = None,
    voxel_channels: Optional[int] = None,
    semantic_heads: Optional[Mapping[str, str]] = None,
    fusion: str = "msdff",
    encoder: str = "pts_middle_encoder",
) -> Tuple[List[ModuleMap], List[str]]:
    """The fusion modules of their MSSF-V sparse encoder (``SparseEncoderVoxelNeXtFuse``).

    Args:
        fusion_blocks: their location (``"x_conv1"``, ...) -> our prefix of the MSDFF / SFF module.
        query_init: our prefix of the :class:`~mssf_blocks.samplers.QueryInit` (their ``query_proj``).
        voxel_channels: ``C_vox`` of the first fusion block (needed with ``query_init``).
        semantic_heads: their location -> our prefix of the :class:`~mssf_blocks.heads.SemanticGuidedHead`.
        fusion: ``"msdff"`` (their ``fusion_block_type='deform'``) or ``"sff"`` (``'simple'``).
        encoder: their encoder's prefix.

    Returns:
        ``(maps, ignore)``: the maps, and the prefix of their query initialiser's ``voxel_fuse.img_transform``
        (a Linear + BN that their forward never calls: it only samples; dead weights) to ignore.
    """
    if fusion not in ("msdff", "sff"):
        raise MSSFError(f"fusion: expected 'msdff' or 'sff', got {fusion!r}")
    maps = [ModuleMap(fusion, f"{encoder}.fusion_blocks.{loc}", ours) for loc, ours in fusion_blocks.items()]
    if query_init is not None:
        maps.append(ModuleMap("query_init", f"{encoder}.query_proj", query_init, voxel_channels))
    for loc, ours in (semantic_heads or {}).items():
        maps.append(ModuleMap("semantic_head", f"{encoder}.seg_heads.{loc}", ours))
    return maps, [f"{encoder}.voxel_fuse.img_transform"]
