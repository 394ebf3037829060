"""The MSSF authors' released MSSF-V checkpoint (``EricLiuhhh/MSSF``, an mmdetection3d checkpoint of their
``VoxelNeXtFuse``) into the mmdet3d MSSF-V built as theirs (``examples/configs/mmdet3d/mssf_voxelnext_vod_authors.py``:
``MSSFSparseEncoder(layout="authors")``, five FPN levels, ``MSSFVoxelNeXtHead``; the older spelling
``authors_layout=True`` builds the same encoder).

:func:`convert_authors_mssf_v` runs the examples' converter
(:func:`mssf_examples.models.authors_checkpoint.convert_authors`, ``layout="mssf_v"``, the one set of name rules)
on a view of the mmdet3d model with the example detector's names (``backbone`` = the encoder's network,
``image_branch.backbone`` / ``.neck`` = ``img_backbone`` / ``img_neck``, ``head`` = the head's
:class:`~mssf_examples.models.heads.authors.AuthorsVoxelNeXtHead`), then renames its keys to the mmdet3d model's.
Their heatmap's classes are permuted from their order (Pedestrian, Cyclist, Car) to the config's
``class_names``. The report says what was mapped, ignored (with the reason) and missing; load with
``strict=True`` when nothing is missing.
"""

from __future__ import annotations

from collections import OrderedDict
from types import SimpleNamespace
from typing import Dict, Mapping, Sequence, Tuple

from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

from ..models.authors_checkpoint import ConversionReport, convert_authors

__all__ = ["convert_authors_mssf_v", "AUTHORS_STAGE_CHANNELS"]

#: their ``base_channels`` (the query initialiser's voxel width), ``voxelnext_voxel005_vod_multimodal_r50pytorch``
AUTHORS_STAGE_CHANNELS = 32

#: the example detector's prefix -> the mmdet3d model's
_PREFIXES = (("backbone.", "pts_middle_encoder.net."), ("image_branch.backbone.", "img_backbone."),
             ("image_branch.neck.", "img_neck."), ("head.", "pts_bbox_head.net."))


class _ExampleNames(nn.Module):
    """The mmdet3d MSSF-V's modules under the example detector's names (the same parameters, not copies)."""

    def __init__(self, model: nn.Module, class_names: Sequence[str]) -> None:
        super().__init__()
        self.backbone = model.pts_middle_encoder.net
        self.image_branch = nn.Module()
        self.image_branch.backbone = model.img_backbone
        self.image_branch.neck = model.img_neck
        self.head = model.pts_bbox_head.net
        self.layout = "authors"
        self.preset = SimpleNamespace(class_names=tuple(class_names))


def _rename(key: str) -> str:
    for src, dst in _PREFIXES:
        if key.startswith(src):
            return dst + key[len(src):]
    raise MSSFError(f"checkpoint: converted key {key!r} has no place in the mmdet3d model")  # (a converter change)


def convert_authors_mssf_v(theirs: Mapping[str, Tensor], model: nn.Module,
                           class_names: Sequence[str]) -> Tuple[Dict[str, Tensor], ConversionReport]:
    """Their state dict (or mmengine checkpoint) -> one for ``model`` (an ``MSSFDetector`` of
    ``mssf_voxelnext_vod_authors.py``), and the report with the mmdet3d model's names.

    Args:
        theirs: their checkpoint (``{'state_dict': ...}``) or state dict.
        model: the built mmdet3d detector.
        class_names: the dataset's classes in the config's order (``class_names`` of the config).

    Raises:
        MSSFError: the model is not built as theirs, or a tensor of theirs maps nowhere / has another shape.
    """
    enc = getattr(model, "pts_middle_encoder", None)
    # MSSFSparseEncoder.authors_layout is True for both spellings (layout="authors", the older authors_layout=True);
    # their MSSF-PP encoder, MSSFPillarEncoder(layout="authors"), has no such attribute and is refused
    has_images = getattr(model, "img_backbone", None) is not None
    if not getattr(enc, "authors_layout", False) or not has_images:
        raise MSSFError("model: expected the MSSF-V built as the authors' (pts_middle_encoder=dict(type="
                        "'MSSFSparseEncoder', layout='authors', ...) with the image branch: "
                        "examples/configs/mmdet3d/mssf_voxelnext_vod_authors.py), got pts_middle_encoder="
                        f"{type(enc).__name__}, layout={getattr(enc, 'layout', None)!r}, "
                        f"{'with' if has_images else 'without'} img_backbone")
    view = _ExampleNames(model, class_names)
    sd, report = convert_authors(theirs, view, layout="mssf_v", stage_channels=AUTHORS_STAGE_CHANNELS)
    target = model.state_dict()
    out = OrderedDict((_rename(k), v) for k, v in sd.items())
    # the model's own module versions: under mmdet3d, spconv modules without version 2 in the metadata load
    # their kernels as mmcv's old (D, H, W, in, out) layout and permute them; these are spconv 2's already
    out._metadata = getattr(target, "_metadata", None)
    report.mapped = [(k, _rename(ours), shape) for k, ours, shape in report.mapped]
    report.missing = [k for k in target if k not in out]
    return out, report
