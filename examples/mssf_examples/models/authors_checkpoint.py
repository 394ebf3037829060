"""Load an MSSF authors' checkpoint (``EricLiuhhh/MSSF``, an mmdetection3d fork) into the example models.

:func:`convert_authors` converts a whole state dict for a target model and reports every tensor of
theirs as **mapped** (their name -> ours, shape checked against the model), or **ignored** (with the
reason); our tensors it did not fill are **missing**. A tensor of theirs that no rule covers, or a shape
that differs, raises :class:`~mssf_blocks.errors.MSSFError` naming it.

Layouts (``layout=``):

* ``"mssf_pp"``: their MSSF-PP into :class:`~mssf_examples.models.backbones.AuthorsPointPillarsBackbone`:
  ``voxel_encoder.pfn_layers.0`` -> ``pfn`` (the linear weight's columns folded,
  :func:`fold_legacy_pfn_columns`), both fusion stages (``middle_encoder.*`` ->
  ``scatter_stage``, ``backbone.*`` -> ``backbone_stage``, through
  :func:`mssf_blocks.weights.authors_pp_keys.mssf_pp_stage_maps`), ``backbone.blocks`` -> ``blocks``,
  ``neck.deblocks`` -> ``deblocks``. Ignored into the backbone alone: the image backbone and neck
  (``img_backbone``, ``img_neck``: mmdet's ResNet-50 and FPN) and the detection head (``bbox_head``:
  their ``Anchor3DHead``), which map onto the detector (below); always: the dead
  ``voxel_fuse.img_transform`` of both stages.

* ``"mssf_v"``: their MSSF-V (``VoxelNeXtFuse`` with ``SparseEncoderVoxelNeXtFuse``) into
  :class:`~mssf_examples.models.backbones.VoxelNeXtBackbone` built with ``authors_layout=True`` and the same
  fusion locations: ``pts_middle_encoder.conv_input`` / ``conv_out`` / ``shared_conv`` by name,
  ``conv1.<j>`` -> ``stages.0.blocks.<j>``, ``conv<i>.0`` -> ``stages.<i-1>.downsample``,
  ``conv<i>.<j>`` -> ``stages.<i-1>.blocks.<j-1>``, the fusion modules, query initialiser and semantic
  head through :func:`mssf_blocks.weights.mssf_v_module_maps` (``stage_channels`` = their
  ``base_channels``, 32). Ignored into the backbone alone: ``img_backbone``, ``img_neck``,
  ``pts_bbox_head`` (their ``VoxelNeXtHead``); always: the dead ``voxel_fuse.img_transform``.

The target may also be the example detector (:class:`~mssf_examples.models.detectors.MSSFDetector` built with
``pillar_layout="authors"``, or ``"voxelnext"`` with an ``authors_layout`` backbone): the backbone's
tensors then go under ``backbone.``, and their image backbone and neck map by name onto the example
image branch (``img_backbone`` -> ``image_branch.backbone``, ``img_neck`` -> ``image_branch.neck``: the
same ResNet / FPN layout; the preset needs ``num_image_levels=5`` and ``image_depth=50``). Built with
``layout="authors"`` (their whole detector), the detection head maps too (:func:`head_pairs`):

* MSSF-PP ``bbox_head.conv_cls`` / ``conv_reg`` / ``conv_dir_cls`` -> ``head.conv_cls`` / ``conv_box`` /
  ``conv_dir``, their output channels permuted from their class order
  (:data:`~mssf_examples.models.heads.authors.AUTHORS_CLASS_ORDER`) to the preset's: an anchor of class ``k`` and
  yaw ``r`` is their anchor ``perm[k] * R + r``, its class logit ``k'`` their ``perm[k']``.
* MSSF-V ``pts_bbox_head.task_heads.0.<branch>.*`` -> ``head.heads.<ours>.*`` (``heatmap`` -> ``hm``,
  ``reg`` -> ``center``, ``height`` -> ``center_z``, ``dim``, ``rot``), the heatmap's outputs permuted.

Otherwise (the examples' own head) the head is reported missing.

``python -m mssf_examples convert-authors CHECKPOINT --out FILE`` runs it and prints the report.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import re
from typing import Callable, Dict, List, Mapping, Optional, Tuple

import torch
from torch import Tensor, nn

from mssf_blocks.weights import mssf_v_module_maps, official_to_ours
from mssf_blocks.weights.authors_pp_keys import mssf_pp_stage_maps
from mssf_blocks.errors import MSSFError

__all__ = ["ConversionReport", "LAYOUTS", "convert_authors", "fold_legacy_pfn_columns", "head_pairs", "unwrap_checkpoint"]

LAYOUTS = ("mssf_pp", "mssf_v")

_PP_RENAMES = (("voxel_encoder.pfn_layers.0.", "pfn."), ("backbone.blocks.", "blocks."), ("neck.deblocks.", "deblocks."))
_IMAGE_IGNORED = (
    ("img_backbone.", "their mmdet ResNet-50 image backbone: the example image branch has another layout"),
    ("img_neck.", "their mmdet FPN: the example image branch has another layout"),
)
_DEAD = "dead: built by their query initialiser, never called"
_PP_IGNORED = _IMAGE_IGNORED + (
    ("bbox_head.", "their Anchor3DHead: maps onto a detector built with layout='authors' only"),
    ("middle_encoder.voxel_fuse.img_transform.", _DEAD),
    ("backbone.voxel_fuse.img_transform.", _DEAD),
)
_V_IGNORED = _IMAGE_IGNORED + (
    ("pts_bbox_head.", "their VoxelNeXtHead: maps onto a detector built with layout='authors' only"),
    ("pts_middle_encoder.voxel_fuse.img_transform.", _DEAD),
)
_ENC = "pts_middle_encoder."
_V_CONV = re.compile(r"pts_middle_encoder\.conv(\d)\.(\d+)\.(.*)")


def _v_rename(key: str) -> Optional[str]:
    """Their ``SparseEncoderVoxelNeXtFuse`` convolutions -> the example ``VoxelNeXtBackbone``."""
    for mine in ("conv_input.", "conv_out.", "shared_conv."):
        if key.startswith(_ENC + mine):
            return key[len(_ENC):]
    m = _V_CONV.fullmatch(key)
    if m is None:
        return None
    stage, j, rest = int(m.group(1)) - 1, int(m.group(2)), m.group(3)
    if stage == 0:  # conv1: two residual blocks, no downsampling
        return f"stages.0.blocks.{j}.{rest}"
    return f"stages.{stage}.downsample.{rest}" if j == 0 else f"stages.{stage}.blocks.{j - 1}.{rest}"


def head_pairs(theirs: Mapping[str, Tensor], model: nn.Module, layout: str) -> Dict[str, Tuple[str, Optional[Callable]]]:
    """Their detection-head tensors -> ``(our name, transform or None)`` for a detector built with
    ``layout="authors"``: ours = ``transform(theirs)``, their class order permuted to the preset's (the
    anchor head's output rows; the VoxelNeXt heatmap's bias, and its 1x1 weight's columns as spconv reads
    it: ``weight.view(in, out)``, see :class:`~mssf_examples.models.heads.authors.SubMConv2dSpconvLayout`)."""
    from .heads.authors import AUTHORS_HEAD_NAMES, class_permutation

    perm = class_permutation(model.preset.class_names)
    pairs: Dict[str, Tuple[str, Optional[Callable]]] = {}
    if layout == "mssf_pp":
        head = model.head
        c, rot = head.num_classes, head.num_anchors_per_location // head.num_classes
        anchor = [perm[k] * rot + r for k in range(c) for r in range(rot)]  # ours a' -> theirs a

        def rows(per: int, cls: bool) -> Callable:
            idx = torch.tensor([anchor[a] * per + (perm[j] if cls else j) for a in range(len(anchor)) for j in range(per)])
            return lambda t: t[idx]

        for mine, ours, idx in (("conv_cls", "conv_cls", rows(c, True)), ("conv_reg", "conv_box", rows(head.code_size, False)),
                                ("conv_dir_cls", "conv_dir", rows(head.num_dir_bins, False))):
            for p in ("weight", "bias"):
                if f"bbox_head.{mine}.{p}" in theirs:
                    pairs[f"bbox_head.{mine}.{p}"] = (f"head.{ours}.{p}", idx)
        return pairs
    names = dict(AUTHORS_HEAD_NAMES)
    prefix = "pts_bbox_head.task_heads.0."
    for k in theirs:
        if not k.startswith(prefix):
            continue
        branch, rest = k[len(prefix):].split(".", 1)
        if branch in names:
            fn = None
            if branch == "heatmap" and rest == "1.bias":
                fn = lambda t: t[list(perm)]  # noqa: E731
            elif branch == "heatmap" and rest == "1.weight":  # (out, 1, 1, in) used as (in, out): permute columns
                fn = lambda t: t.reshape(t.shape[3], t.shape[0])[:, list(perm)].reshape(t.shape)  # noqa: E731
            pairs[k] = (f"head.heads.{names[branch]}.{rest}", fn)
    return pairs


@dataclass
class ConversionReport:
    """What :func:`convert_authors` did with every tensor."""

    mapped: List[Tuple[str, str, Tuple[int, ...]]] = field(default_factory=list)  # theirs, ours, shape
    ignored: List[Tuple[str, str]] = field(default_factory=list)  # theirs, reason
    missing: List[str] = field(default_factory=list)  # ours, not filled

    def summary(self) -> str:
        lines = [f"mapped {len(self.mapped)}, ignored {len(self.ignored)}, missing {len(self.missing)}"]
        reasons: Dict[str, int] = {}
        for _, why in self.ignored:
            reasons[why] = reasons.get(why, 0) + 1
        lines += [f"  ignored {n}: {why}" for why, n in reasons.items()]
        lines += [f"  missing: {k}" for k in self.missing]
        return "\n".join(lines)


def fold_legacy_pfn_columns(weight: Tensor) -> Tensor:
    """Their ``PillarFeatureNet`` linear weight ``(C_out, C + 6)`` -> ours, exactly.

    mmdet3d's ``PillarFeatureNet(legacy=True)`` (the default, and their config's) computes the pillar-centre
    offsets in place in the points' first three columns, so its input is
    ``[xyz - centre, rest, xyz - mean, xyz - centre]``; ours is ``[xyz, rest, xyz - mean, xyz - centre]``.
    The linear map has no bias, so their first three columns fold into the last three and ours read
    zero weight on the raw ``xyz``.
    """
    if weight.dim() != 2 or weight.shape[1] < 9:
        raise MSSFError(f"voxel_encoder.pfn_layers.0.linear.weight: expected (C_out, C + 6), got {tuple(weight.shape)}")
    out = weight.clone()
    out[:, -3:] = weight[:, -3:] + weight[:, :3]
    out[:, :3] = 0
    return out


def unwrap_checkpoint(obj) -> Mapping[str, Tensor]:
    """An mmengine checkpoint's ``state_dict`` (or the mapping itself)."""
    if isinstance(obj, Mapping) and isinstance(obj.get("state_dict"), Mapping):
        obj = obj["state_dict"]
    if not isinstance(obj, Mapping) or not all(isinstance(v, Tensor) for v in obj.values()):
        raise MSSFError("checkpoint: expected a state dict of tensors or a dict with one under 'state_dict'")
    return obj


def convert_authors(theirs: Mapping[str, Tensor], model: nn.Module, layout: str = "mssf_pp",
                    stage_channels: int = 64) -> Tuple[Dict[str, Tensor], ConversionReport]:
    """Their state dict -> one for ``model`` (load it with ``strict=True`` when nothing is missing).

    Raises:
        MSSFError: a tensor of theirs that no rule maps or ignores, or whose shape differs from the
            model's tensor (both named).
    """
    if layout not in LAYOUTS:
        raise MSSFError(f"layout: expected one of {LAYOUTS}, got {layout!r}")
    theirs = unwrap_checkpoint(theirs)
    target = model.state_dict()
    report = ConversionReport()
    out: Dict[str, Tensor] = {}
    # an example detector (MSSFDetector): its backbone under "backbone.", its image branch (mmdet's
    # ResNet / FPN names) under "image_branch."; the detection head stays unmapped (missing)
    detector = hasattr(model, "image_branch") and hasattr(model, "head") and hasattr(model, "backbone")
    bb = "backbone." if detector else ""
    table = _PP_IGNORED if layout == "mssf_pp" else _V_IGNORED
    if detector and model.image_branch is not None:
        table = tuple(t for t in table if t not in _IMAGE_IGNORED)
    authors_head = detector and getattr(model, "layout", "paper") == "authors"
    if authors_head:  # their detection head maps onto the head built as theirs
        table = tuple(t for t in table if not t[0].startswith(("bbox_head.", "pts_bbox_head.")))
    ignored = {k: why for k in theirs for p, why in table if k.startswith(p)}
    head_map = head_pairs(theirs, model, layout) if authors_head else {}
    image = {}
    if detector and model.image_branch is not None:
        image = {k: dst + k[len(src):] for k in theirs
                 for src, dst in (("img_backbone.", "image_branch.backbone."), ("img_neck.", "image_branch.neck."))
                 if k.startswith(src)}
    if layout == "mssf_pp":
        renamed = {k: bb + dst + k[len(src):] for k in theirs for src, dst in _PP_RENAMES if k.startswith(src)}
        stages = []
        for stage, enc, ours in (("scatter", "middle_encoder", "scatter_stage"), ("backbone", "backbone", "backbone_stage")):
            maps, ignore = mssf_pp_stage_maps(stage, bb + ours, stage_channels)
            stages.append((enc, maps, ignore))
    else:
        renamed = {k: bb + v for k in theirs if k not in ignored for v in [_v_rename(k)] if v is not None}
        locs = sorted({k.split(".")[2] for k in theirs if k.startswith(_ENC + "fusion_blocks.")})
        heads = sorted({k.split(".")[2] for k in theirs if k.startswith(_ENC + "seg_heads.")})
        simple = any(".img_transform." in k for k in theirs if k.startswith(_ENC + "fusion_blocks."))
        maps, ignore = mssf_v_module_maps(
            {loc: f"{bb}stages.{int(loc[-1]) - 1}.fusion" for loc in locs},
            query_init=None if simple else f"{bb}stages.0.query_init", voxel_channels=stage_channels,
            semantic_heads={loc: f"{bb}stages.{int(loc[-1]) - 1}.semantic_head" for loc in heads},
            fusion="sff" if simple else "msdff")
        stages = [("pts_middle_encoder", maps, ignore)]
    renamed.update(image)
    renamed.update({k: ours for k, (ours, _) in head_map.items()})
    stage_keys = {}
    for enc, maps, ignore in stages:
        keys = [k for k in theirs if k.startswith(enc + ".") and k not in ignored and k not in renamed]
        # strict=False: what a stage lacks is counted below, against the whole model (report.missing),
        # after the unknown tensors of a wrong layout are named
        converted = official_to_ours({k: theirs[k] for k in keys}, maps, ignore, strict=False)
        for m in maps:  # the name pairs (the converter's rules, per module)
            mine = [k for k in keys if k.startswith(m.theirs + ".")]
            rules = dict(m.rules([k[len(m.theirs) + 1:] for k in mine]))
            stage_keys.update({k: f"{m.ours}.{rules[k[len(m.theirs) + 1:]]}" for k in mine})
        out.update(converted)
    unknown = [k for k in theirs if k not in ignored and k not in renamed and k not in stage_keys]
    if unknown:
        shown = ", ".join(unknown[:12]) + (f", ... ({len(unknown)} in all)" if len(unknown) > 12 else "")
        raise MSSFError(f"checkpoint: {len(unknown)} tensor(s) of theirs map to nothing in layout {layout!r}: {shown}")
    out.update({renamed[k]: theirs[k] for k in renamed})
    out.update({ours: fn(theirs[k]) for k, (ours, fn) in head_map.items() if fn is not None})
    pfn = "voxel_encoder.pfn_layers.0.linear.weight"
    if layout == "mssf_pp" and pfn in renamed:
        out[renamed[pfn]] = fold_legacy_pfn_columns(theirs[pfn])
    pairs = {**renamed, **stage_keys}
    for k, ours in pairs.items():
        if ours not in target:
            raise MSSFError(f"checkpoint: {k} maps to {ours}, which the model does not have")
        if tuple(out[ours].shape) != tuple(target[ours].shape):
            raise MSSFError(f"checkpoint: {k} has shape {tuple(out[ours].shape)}, the model's {ours} "
                            f"{tuple(target[ours].shape)}")
        report.mapped.append((k, ours, tuple(out[ours].shape)))
    report.ignored = sorted(ignored.items())
    report.missing = [k for k in target if k not in out]
    return out, report

