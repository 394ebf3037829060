"""The MSSF authors' released MSSF-PP checkpoint (``EricLiuhhh/MSSF``) into this project's mmdet3d MSSF-PP.

Their MSSF-PP is an mmdet3d ``VoxelNetFuse`` (config ``pointpillars_hv_secfpn_8xb6-160e_vod-3d-3class_mm_bb_bevfeat_
lr0001``); the target is ``MSSFDetector`` built from ``examples/configs/mmdet3d/mssf_pointpillars_vod_authors.py``
(``MSSFPillarEncoder(layout="authors")``, five FPN levels). :func:`convert_authors_mmdet3d` maps every tensor of
theirs and reports it as **mapped** (their name -> ours, shape checked), **ignored** (with the reason) or, for
ours, **missing**:

* ``voxel_encoder.*``, ``middle_encoder.*``, ``backbone.*``, ``neck.*`` -> ``pts_middle_encoder.net.*``: the
  example converter's rules (:func:`mssf_examples.models.authors_checkpoint.convert_authors`, layout
  ``"mssf_pp"``: the PFN's legacy columns folded, both fusion stages through
  :func:`mssf_blocks.weights.mssf_pp_stage_maps`, ``blocks`` / ``deblocks`` by name);
* ``img_backbone.*``, ``img_neck.*`` -> the same names (mmdet's ``ResNet`` and ``FPN`` on both sides);
* ``bbox_head.*`` -> ``pts_bbox_head.*`` (mmdet3d's ``Anchor3DHead`` on both sides), the output channels of
  ``conv_cls`` / ``conv_reg`` / ``conv_dir_cls`` reordered from their class order (Pedestrian, Cyclist, Car)
  to the config's (:func:`mssf_examples.models.authors_checkpoint.head_pairs`: anchor ``k * R + r`` is their
  ``perm[k] * R + r``, class logit ``k`` their ``perm[k]``);
* ignored: the dead ``voxel_fuse.img_transform`` of both stages (built by their query initialiser, never called).

``python -m mssf_examples.mmdet3d convert-authors CHECKPOINT --config CONFIG --out FILE`` (:func:`run`) builds the
config's model, converts, loads the result with ``strict=True``, prints the report and writes an mmengine
checkpoint (``state_dict``, ``meta``) that ``test CONFIG FILE`` and ``load_from`` read.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Dict, Mapping, Sequence, Tuple

from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

__all__ = ["convert_authors_mmdet3d", "run"]

_NET = "pts_middle_encoder.net."
_SAME_NAME = ("img_backbone.", "img_neck.")
#: the example head's names (head_pairs) -> mmdet3d's Anchor3DHead's
_HEAD_NAMES = {"head.conv_cls.": "pts_bbox_head.conv_cls.", "head.conv_box.": "pts_bbox_head.conv_reg.",
               "head.conv_dir.": "pts_bbox_head.conv_dir_cls."}


def _head_pairs(theirs: Mapping[str, Tensor], head: nn.Module,
                class_names: Sequence[str]) -> Dict[str, Tuple[str, object]]:
    """Their ``bbox_head`` tensors -> ``(our mmdet3d name, reorder)``, through the example converter's anchor rule."""
    from ..models.authors_checkpoint import head_pairs

    rotations = head.num_anchors // head.num_classes
    if rotations * head.num_classes != head.num_anchors:
        raise MSSFError(f"pts_bbox_head: expected one anchor size per class ({head.num_classes}) and the same "
                        f"rotations, got {head.num_anchors} anchors per location")
    view = SimpleNamespace(preset=SimpleNamespace(class_names=tuple(class_names)),
                           head=SimpleNamespace(num_classes=head.num_classes, num_anchors_per_location=head.num_anchors,
                                                code_size=head.box_code_size, num_dir_bins=2))
    pairs = {}
    for k, (ours, fn) in head_pairs(theirs, view, "mssf_pp").items():
        prefix = next(p for p in _HEAD_NAMES if ours.startswith(p))
        pairs[k] = (_HEAD_NAMES[prefix] + ours[len(prefix):], fn)
    return pairs


def convert_authors_mmdet3d(theirs: Mapping[str, Tensor], model: nn.Module,
                            class_names: Sequence[str] = ("Car", "Pedestrian", "Cyclist")):
    """Their MSSF-PP state dict -> one for ``model`` (``MSSFDetector`` with ``MSSFPillarEncoder(layout="authors")``).

    Args:
        theirs: their checkpoint (mmengine's ``{'state_dict': ...}`` or the state dict).
        model: the built mmdet3d model.
        class_names: the config's class order (label ``k`` of ``model``), a permutation of theirs.

    Returns:
        ``(state_dict, report)``: load it with ``model.load_state_dict(state_dict, strict=True)`` when
        ``report.missing`` is empty; ``report`` is :class:`~mssf_examples.models.authors_checkpoint.ConversionReport`.

    Raises:
        MSSFError: a model not in their layout, a tensor of theirs that no rule maps or ignores, or a shape that
            differs from the model's (both named).
    """
    from ..models.authors_checkpoint import ConversionReport, convert_authors, unwrap_checkpoint

    enc = getattr(model, "pts_middle_encoder", None)
    if getattr(enc, "layout", None) != "authors" or getattr(model, "pts_bbox_head", None) is None:
        raise MSSFError("model: expected an MSSFDetector with pts_middle_encoder=MSSFPillarEncoder(layout='authors') "
                        "and an Anchor3DHead (examples/configs/mmdet3d/mssf_pointpillars_vod_authors.py), got "
                        f"{type(enc).__name__} with layout {getattr(enc, 'layout', None)!r}")
    theirs = unwrap_checkpoint(theirs)
    net_sd, net_report = convert_authors(theirs, enc.net, layout="mssf_pp")
    out = {_NET + k: v for k, v in net_sd.items()}
    report = ConversionReport(mapped=[(t, _NET + o, s) for t, o, s in net_report.mapped])
    head = _head_pairs(theirs, model.pts_bbox_head, class_names)
    moved = {k: (k, None) for k in theirs if k.startswith(_SAME_NAME)}
    moved.update(head)
    target = model.state_dict()
    for k, (ours, fn) in moved.items():
        value = theirs[k] if fn is None else fn(theirs[k])
        if ours not in target:
            raise MSSFError(f"checkpoint: {k} maps to {ours}, which the model does not have")
        if tuple(value.shape) != tuple(target[ours].shape):
            raise MSSFError(f"checkpoint: {k} has shape {tuple(value.shape)}, the model's {ours} "
                            f"{tuple(target[ours].shape)}")
        out[ours] = value
        report.mapped.append((k, ours, tuple(value.shape)))
    # the example converter ignores the image branch and the head (the backbone alone); they are mapped here
    report.ignored = [(k, why) for k, why in net_report.ignored if k not in moved]
    left = [k for k in theirs if k.startswith("bbox_head.") and k not in head]
    if left:
        raise MSSFError(f"checkpoint: {len(left)} tensor(s) of their bbox_head map to nothing: {left[:12]}")
    report.missing = [k for k in target if k not in out]
    return out, report


def run(checkpoint: str, config: str, out: str) -> int:
    """``convert-authors``: build ``config``'s model, convert ``checkpoint``, load strictly, print, write ``out``."""
    import torch
    from mmdet3d.registry import MODELS
    from mmengine.registry import init_default_scope

    from .checkpoints import load_from_local_weights_only
    from .cli import load_config

    cfg = load_config(config)
    init_default_scope(cfg.get("default_scope", "mmdet3d"))
    model = MODELS.build(cfg.model)
    theirs = load_from_local_weights_only(checkpoint, map_location="cpu")
    state, report = convert_authors_mmdet3d(theirs, model, cfg.get("class_names", ("Car", "Pedestrian", "Cyclist")))
    print(report.summary())
    if report.missing:
        raise MSSFError(f"checkpoint: {len(report.missing)} tensor(s) of the model not filled (above); is {config} "
                        "configured as theirs (mssf_pointpillars_vod_authors.py)?")
    model.load_state_dict(state, strict=True)  # every tensor of the model, no other
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"meta": {"converted_from": str(checkpoint), "config": str(config)},
                "state_dict": {k: v.contiguous() for k, v in state.items()}}, path)
    print(f"wrote {path}")
    return 0
