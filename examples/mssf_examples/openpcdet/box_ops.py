"""Pure-torch stand-ins for the box operations of OpenPCDet's compiled ``iou3d_nms_cuda``.

:func:`use_pure_torch_box_ops` replaces, in ``pcdet.ops.iou3d_nms.iou3d_nms_utils``, the rotated NMS
(``nms_gpu``) and the rotated IoUs (``boxes_iou_bev``, ``boxes_iou3d_gpu``) with the project's
(:func:`mssf_examples.models.ops.nms.nms_bev`, :func:`mssf_examples.models.ops.iou.box_iou_bev` /
:func:`~mssf_examples.models.ops.iou.box_iou_3d`; the same definitions: greedy NMS in descending score
order, a box suppressed when its rotated BEV IoU with a kept box exceeds the threshold). OpenPCDet's
post-processing (``model_nms_utils``, ``Detector3DTemplate.generate_recall_record``) looks these up on
the module at call time, so evaluation runs on a machine without the CUDA extension (or on any device).
"""

from __future__ import annotations

from typing import Dict

__all__ = ["use_pure_torch_box_ops"]


def _nms_gpu(boxes, scores, thresh, pre_maxsize=None, **kwargs):
    from ..models.ops.nms import nms_bev

    return nms_bev(boxes[:, :7].contiguous(), scores, float(thresh), pre_maxsize), None


def _boxes_iou_bev(boxes_a, boxes_b):
    from ..models.ops.iou import box_iou_bev

    return box_iou_bev(boxes_a[:, :7], boxes_b[:, :7])


def _boxes_iou3d(boxes_a, boxes_b):
    from ..models.ops.iou import box_iou_3d

    return box_iou_3d(boxes_a[:, :7], boxes_b[:, :7])


def use_pure_torch_box_ops() -> Dict[str, object]:
    """Patch ``iou3d_nms_utils``; returns the replaced originals (``{name: function}``) to restore them."""
    from pcdet.ops.iou3d_nms import iou3d_nms_utils

    new = {"nms_gpu": _nms_gpu, "boxes_iou_bev": _boxes_iou_bev, "boxes_iou3d_gpu": _boxes_iou3d}
    old = {name: getattr(iou3d_nms_utils, name) for name in new}
    for name, fn in new.items():
        setattr(iou3d_nms_utils, name, fn)
    return old
