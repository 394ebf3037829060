"""``VoDMetric``: View-of-Delft evaluation (entire annotated area and driving corridor) for mmdet3d.

Registered in ``mmdet3d.registry.METRICS`` by :mod:`mssf_examples.mmdet3d.plugin`. It evaluates the
predictions with the project's kit-exact VoD protocol (:func:`mssf_examples.evaluation.metrics.evaluate`,
``protocol="vod"``, the rules of ``vod-tudelft``'s ``kitti_official_evaluate.py``) against each frame's
own ``label_2`` and calibration text, which :mod:`~mssf_examples.mmdet3d.infos` stores in the info file
(every type, ``DontCare`` and neighbouring classes included, as the kit reads them). mmdet3d's
``KittiMetric`` is not this protocol (no corridor, KITTI difficulties).

Keys (after mmengine's ``VoD/`` prefix): ``<region>/<class or mAP>/<AP3D_R11|AP3D_R40|APBEV_R11|APBEV_R40>``
with ``region`` ``entire_area`` or ``driving_corridor``; the paper's Table I reports ``AP3D_R11``.

``TJ4DMetric``: the same for TJ4DRadSet with the project's TJ4D protocol (``protocol="tj4d"``,
:mod:`mssf_examples.evaluation.tj4d`: the MSSF authors' evaluation, cumulative range bins, their 41/40 "R40"),
against the ``tj4d`` texts of :func:`~mssf_examples.mmdet3d.infos.create_tj4d_infos`; keys
``TJ4D/<range_0_50|range_0_70|range_all>/<Car|Pedestrian|Cyclist|Truck|mAP>/<...>``; the paper's Table III
reports ``range_0_70``, ``AP3D_R40`` and ``APBEV_R40``.
"""

from __future__ import annotations

import math
import pickle
from typing import Dict, List, Optional, Sequence

import torch
from mmengine.evaluator import BaseMetric
from mmengine.logging import MMLogger

from mssf_blocks.errors import MSSFError

from ..data.kitti_io import TJ4D_CLASSES, VOD_CLASSES, parse_calibration, parse_labels
from ..evaluation.metrics import evaluate, format_table

__all__ = ["VoDMetric", "TJ4DMetric", "predictions_from_mmdet3d"]


def predictions_from_mmdet3d(pred: Dict, calib, image_size) -> Dict:
    """mmdet3d ``pred_instances_3d`` (LiDAR boxes, bottom centre) -> the evaluation's sensor-frame dict."""
    boxes = getattr(pred["bboxes_3d"], "tensor", pred["bboxes_3d"])[:, :7].detach().cpu().to(torch.float64).clone()
    boxes[:, 2] += boxes[:, 5] / 2  # bottom-face centre -> box centre
    return {"boxes": boxes, "scores": pred["scores_3d"].detach().cpu().to(torch.float64),
            "labels": pred["labels_3d"].detach().cpu().long(), "calib": calib, "image_size": tuple(image_size)}


class VoDMetric(BaseMetric):
    """VoD AP per class and mAP, entire annotated area and driving corridor.

    Args:
        ann_file: the info file of the evaluated split (from ``python -m mssf_examples.mmdet3d infos``).
        classes: class names in label order (default the VoD classes Car, Pedestrian, Cyclist).
        collect_device, prefix: as ``BaseMetric``.
    """

    default_prefix = "VoD"
    #: the evaluation protocol, the default classes, the info files' text key and the logged table's metric
    protocol, default_classes, text_key, table_metric = "vod", VOD_CLASSES, "vod", "AP3D_R11"

    def __init__(self, ann_file: str, classes: Optional[Sequence[str]] = None, collect_device: str = "cpu",
                 prefix: Optional[str] = None) -> None:
        super().__init__(collect_device=collect_device, prefix=prefix)
        self.ann_file = str(ann_file)
        self.classes = tuple(classes) if classes is not None else self.default_classes

    def process(self, data_batch: Dict, data_samples: Sequence[Dict]) -> None:
        for s in data_samples:
            pred = s["pred_instances_3d"]
            self.results.append({"sample_idx": s["sample_idx"],
                                 "pred": {k: pred[k].to("cpu") for k in ("bboxes_3d", "scores_3d", "labels_3d")}})

    def _frames(self) -> List[Dict]:
        """The ``vod`` (``tj4d``) entry of every frame, in data-list order (mmengine's ``sample_idx`` is the
        dataset index)."""
        with open(self.ann_file, "rb") as f:
            infos = pickle.load(f)
        frames = []
        for info in infos["data_list"]:
            if self.text_key not in info:
                raise MSSFError(f"ann_file {self.ann_file}: infos without the {self.text_key!r} label/calibration "
                                f"text; write them with python -m mssf_examples.mmdet3d infos --dataset {self.text_key}")
            frames.append(info[self.text_key])
        return frames

    def compute_metrics(self, results: List[Dict]) -> Dict[str, float]:
        frames = self._frames()
        preds, gts = [], []
        for r in results:
            if not 0 <= int(r["sample_idx"]) < len(frames):
                raise MSSFError(f"sample_idx {r['sample_idx']}: not in ann_file {self.ann_file}")
            v = frames[r["sample_idx"]]
            calib = parse_calibration(v["calib_text"], f"calib of {r['sample_idx']}")
            preds.append(predictions_from_mmdet3d(r["pred"], calib, v["image_size"]))
            gts.append(parse_labels(v["label_text"], f"labels of {r['sample_idx']}"))
        res = evaluate(preds, gts, self.classes, protocol=self.protocol)
        MMLogger.get_current_instance().info("\n" + format_table(res, metric=self.table_metric))
        out = {}
        for region, per_class in res.items():
            for cls, values in per_class.items():
                for key in ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40"):
                    val = float(values[key])
                    out[f"{region}/{cls}/{key}"] = val if not math.isnan(val) else float("nan")
        return out


class TJ4DMetric(VoDMetric):
    """TJ4DRadSet AP per class and mAP for the ranges 0-50 m, 0-70 m and all (the project's ``protocol="tj4d"``).

    Args: as :class:`VoDMetric` (default classes Car, Pedestrian, Cyclist, Truck).
    """

    default_prefix = "TJ4D"
    protocol, default_classes, text_key, table_metric = "tj4d", TJ4D_CLASSES, "tj4d", "AP3D_R40"
