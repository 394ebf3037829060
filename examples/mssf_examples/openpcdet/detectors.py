"""MSSF-SECOND, MSSF-VoxelNeXt, MSSF-CenterPoint and MSSF-PP as OpenPCDet detectors (``MODEL.NAME: MSSFSECONDNet``
/ ``MSSFVoxelNeXt`` / ``MSSFCenterPoint`` / ``MSSFPointPillar``).

Each is OpenPCDet's ``SECONDNet`` / ``VoxelNeXt`` / ``CenterPoint`` / ``PointPillar`` with two changes:

* an image branch (``MODEL.IMAGE_BRANCH``, :class:`~mssf_examples.openpcdet.image_module.OpenPCDetImageBranch`)
  runs first in ``module_list`` (before ``vfe`` and ``backbone_3d``) and writes the FPN levels the
  fusion backbone reads; with ``BACKBONE_3D.NUM_FUSION_BLOCKS: 0`` (radar-only) there is none;
* ``get_training_loss(batch_dict)`` adds the semantic-guided head's focal loss
  (``backbone_3d.get_loss``, ``tb_dict['loss_mssf_seg']``) to the dense head's.

MSSF-PP fuses in its 2D backbone: read ``BACKBONE_2D`` / ``backbone_2d`` for ``BACKBONE_3D`` /
``backbone_3d`` there (``FUSION_MODULE``).

The configuration is checked when the model is built; errors name the key (image levels / channels
against ``BACKBONE_3D.IMAGE_CHANNELS``, ``DATA_CONFIG.GET_ITEM_LIST`` without images, ``AUG_ORDER``
against ``DATA_AUGMENTOR.AUG_CONFIG_LIST``). Importing this module imports OpenPCDet.
"""

from __future__ import annotations

import warnings
from typing import Any, Dict

import torch
from pcdet.models.detectors.centerpoint import CenterPoint
from pcdet.models.detectors.pointpillar import PointPillar
from pcdet.models.detectors.second_net import SECONDNet
from pcdet.models.detectors.voxelnext import VoxelNeXt

from mssf_blocks.errors import MSSFError
from mssf_blocks.integrations.openpcdet import DEFAULT_AUGMENTOR_ORDER, augmentor_order

from .image_module import IMAGE_BRANCH_DEFAULTS, OpenPCDetImageBranch

__all__ = ["MSSFSECONDNet", "MSSFVoxelNeXt", "MSSFCenterPoint", "MSSFPointPillar", "MSSF_DETECTORS",
           "check_mssf_config"]


def check_mssf_config(model_cfg: Any, dataset_cfg: Any, fusion_key: str = "BACKBONE_3D") -> bool:
    """Check a model config against its dataset config; ``True`` when the backbone fuses the image.

    ``fusion_key``: the ``MODEL`` entry holding the fusion settings (``BACKBONE_2D`` for MSSF-PP)."""
    bb = model_cfg[fusion_key]
    fuses = int(bb.get("NUM_FUSION_BLOCKS", 0) or 0) > 0
    aug = dataset_cfg.get("DATA_AUGMENTOR", None)
    if aug is not None:
        expected = augmentor_order(aug)
        given = bb.get("AUG_ORDER", None)
        given = DEFAULT_AUGMENTOR_ORDER if given is None else tuple(given)
        if fuses and given != expected:
            raise MSSFError(f"MODEL.{fusion_key}.AUG_ORDER: {list(given)} does not match the order in which "
                            f"DATA_CONFIG.DATA_AUGMENTOR.AUG_CONFIG_LIST applies the geometric augmentations "
                            f"(after DISABLE_AUG_LIST): {list(expected)}")
    if not fuses:
        return False
    items = list(dataset_cfg.get("GET_ITEM_LIST", ["points"]))
    need = [k for k in ("points", "images", "calib_matricies") if k not in items]
    if need:
        raise MSSFError(f"DATA_CONFIG.GET_ITEM_LIST: MSSF fusion (MODEL.{fusion_key}.NUM_FUSION_BLOCKS > 0) needs "
                        f"{need} from the dataset, got {items}")
    if "IMAGE_BRANCH" not in model_cfg:
        raise MSSFError(f"MODEL.IMAGE_BRANCH: required when MODEL.{fusion_key}.NUM_FUSION_BLOCKS > 0 (the ResNet + FPN "
                        "whose levels the fusion blocks sample)")
    ib = {**IMAGE_BRANCH_DEFAULTS, **dict(model_cfg.IMAGE_BRANCH)}
    levels = [int(ib["FPN_CHANNELS"])] * int(ib["NUM_OUTS"])
    declared = [int(c) for c in bb.get("IMAGE_CHANNELS", None) or []]
    if declared != levels:
        raise MSSFError(f"MODEL.{fusion_key}.IMAGE_CHANNELS: the image branch (MODEL.IMAGE_BRANCH FPN_CHANNELS "
                        f"{ib['FPN_CHANNELS']}, NUM_OUTS {ib['NUM_OUTS']}) gives levels of {levels} channels, the "
                        f"backbone declares {declared}")
    key = bb.get("IMAGE_FEATURES_KEY", "image_fpn")
    if key != ib["OUTPUT_KEY"]:
        raise MSSFError(f"MODEL.{fusion_key}.IMAGE_FEATURES_KEY: {key!r}, but MODEL.IMAGE_BRANCH.OUTPUT_KEY writes "
                        f"{ib['OUTPUT_KEY']!r}")
    return True


class _MSSFDetector:
    """What the MSSF detectors add to their OpenPCDet parent (listed first in the bases)."""

    #: the module that fuses (its config key in ``MODEL`` and its attribute: ``get_loss`` gives the seg loss)
    FUSION_MODULE = "backbone_3d"

    def _add_image_branch(self, model_cfg: Any, dataset: Any) -> None:
        self.image_branch = None
        if check_mssf_config(model_cfg, dataset.dataset_cfg, self.FUSION_MODULE.upper()):
            self.image_branch = OpenPCDetImageBranch(model_cfg.IMAGE_BRANCH)
            self.module_list.insert(0, self.image_branch)  # runs before vfe / backbone_3d

    def forward(self, batch_dict: Dict[str, Any]):
        coords = batch_dict.get("voxel_coords", None)
        if coords is None:  # a dynamic VFE (VoxelNeXt-2D) groups the points itself
            coords = batch_dict.get("points", None)
        if coords is not None and coords.shape[0] == 0:  # a shape: no host read
            return self._batch_without_voxels(batch_dict)
        for cur_module in self.module_list:
            batch_dict = cur_module(batch_dict)
        if self.training:
            loss, tb_dict, disp_dict = self.get_training_loss(batch_dict)
            return {"loss": loss}, tb_dict, disp_dict
        return self.post_processing(batch_dict)

    def _load_state_dict(self, model_state_disk, *, strict=True):
        """OpenPCDet's loading (``load_params_from_file``, ``load_params_with_optimizer``), then: an image branch
        waiting for a trained checkpoint's weights must have found all of them there."""
        state_dict, updated = super()._load_state_dict(model_state_disk, strict=strict)
        branch = getattr(self, "image_branch", None)
        if branch is not None and branch.awaiting_checkpoint:
            aliases = tuple(f"{name}." for name, m in self.named_modules(remove_duplicate=False) if m is branch)
            keys = [k for k in state_dict if k.startswith(aliases)]  # image_branch.* and module_list.0.*
            missing = [k for k in keys if k not in updated]
            if missing:
                raise MSSFError(f"checkpoint: the image branch's weights were to come from it (MODEL.IMAGE_BRANCH."
                                f"CHECKPOINT {branch.cfg['CHECKPOINT']!r} is not there), but it lacks {len(missing)} of "
                                f"its {len(keys)} tensors (e.g. {missing[:3]}): not a checkpoint of this detector?")
            branch.awaiting_checkpoint = False
        return state_dict, updated

    def _batch_without_voxels(self, batch_dict: Dict[str, Any]):
        """A batch whose frames hold no radar point in range (VoD has such frames at range; a batch of one
        such frame is then empty): spconv cannot run on zero voxels. Evaluation: no detection for each frame
        (its ground truth still counts in the recall). Training: the batch is skipped with a counted warning:
        the loss is a zero that reaches no parameter, so the optimizer step leaves every weight without a
        gradient (torch's optimizers skip those; OpenPCDet's ``adam_onecycle`` still applies its decoupled
        weight decay)."""
        ref = next(self.parameters())
        batch_size = int(batch_dict["batch_size"])
        if self.training:
            self.batches_without_voxels = getattr(self, "batches_without_voxels", 0) + 1
            if self.batches_without_voxels == 1:
                warnings.warn(f"{type(self).__name__}: a training batch of {batch_size} frame(s) without any voxel "
                              "(no radar point in POINT_CLOUD_RANGE) is skipped: loss 0, no gradient. Counted in "
                              "tb_dict['batches_without_voxels'] (the model's batches_without_voxels: all so far); "
                              "this warning is not repeated", stacklevel=2)
            loss = ref.new_zeros((), requires_grad=True)
            return {"loss": loss}, {"loss": 0.0, "batches_without_voxels": self.batches_without_voxels}, {}
        boxes = ref.new_zeros((0, 7))
        preds = [{"pred_boxes": boxes, "pred_scores": ref.new_zeros((0,)),
                  "pred_labels": torch.zeros(0, dtype=torch.long, device=ref.device)} for _ in range(batch_size)]
        recall: Dict[str, Any] = {}
        for b in range(batch_size):
            recall = self.generate_recall_record(box_preds=boxes, recall_dict=recall, batch_index=b, data_dict=batch_dict,
                                                 thresh_list=self.model_cfg.POST_PROCESSING.RECALL_THRESH_LIST)
        return preds, recall

    def get_training_loss(self, batch_dict: Dict[str, Any] = None):
        loss, tb_dict, disp_dict = super().get_training_loss()
        if batch_dict is not None and "mssf_seg_logits" in batch_dict:
            loss_seg, tb_seg = getattr(self, self.FUSION_MODULE).get_loss(batch_dict)
            loss = loss + loss_seg
            tb_dict.update(tb_seg)
        tb_dict["loss"] = float(loss.detach())
        return loss, tb_dict, disp_dict


class MSSFSECONDNet(_MSSFDetector, SECONDNet):
    """SECOND (``MSSFVoxelBackBone8x`` + ``HeightCompression`` + ``BaseBEVBackbone`` + ``AnchorHeadSingle``)
    with the MSSF image branch and semantic loss."""

    def __init__(self, model_cfg, num_class, dataset):
        SECONDNet.__init__(self, model_cfg=model_cfg, num_class=num_class, dataset=dataset)
        self._add_image_branch(model_cfg, dataset)


class MSSFVoxelNeXt(_MSSFDetector, VoxelNeXt):
    """The paper's MSSF-V: ``MSSFVoxelResBackBone8xVoxelNeXt`` (doubled widths) + ``VoxelNeXtHead``.

    ``DENSE_HEAD.NAME: VoxelNeXtHead`` builds :class:`~mssf_examples.openpcdet.voxelnext_head.SparseFrameVoxelNeXtHead`
    (the stock head, same parameters, that trains and evaluates on radar frames with few or no voxels)."""

    def __init__(self, model_cfg, num_class, dataset):
        VoxelNeXt.__init__(self, model_cfg=model_cfg, num_class=num_class, dataset=dataset)
        self._add_image_branch(model_cfg, dataset)

    def build_dense_head(self, model_info_dict):
        import pcdet.models.dense_heads as dense_heads

        from .voxelnext_head import SparseFrameVoxelNeXtHead

        name = self.model_cfg.get("DENSE_HEAD", {}).get("NAME", None)
        if name != "VoxelNeXtHead":
            return super().build_dense_head(model_info_dict)
        # OpenPCDet's own construction, with the sparse-frame head in the registry's place for this call only
        stock = dense_heads.__all__[name]
        dense_heads.__all__[name] = SparseFrameVoxelNeXtHead
        try:
            return super().build_dense_head(model_info_dict)
        finally:
            dense_heads.__all__[name] = stock


class MSSFCenterPoint(_MSSFDetector, CenterPoint):
    """CenterPoint (``MSSFVoxelResBackBone8x`` + ``HeightCompression`` + ``BaseBEVBackbone`` + ``CenterHead``,
    OpenPCDet's voxel CenterPoint) with the MSSF image branch and semantic loss."""

    def __init__(self, model_cfg, num_class, dataset):
        CenterPoint.__init__(self, model_cfg=model_cfg, num_class=num_class, dataset=dataset)
        self._add_image_branch(model_cfg, dataset)
        head = self.dense_head
        cells = int(head.grid_size[0] // head.feature_map_stride) * int(head.grid_size[1] // head.feature_map_stride)
        k = int(head.model_cfg.POST_PROCESSING.MAX_OBJ_PER_SAMPLE)
        if k > cells:  # CenterHead's decoding takes the top k of each class's heatmap: torch.topk fails later
            raise MSSFError(f"MODEL.DENSE_HEAD.POST_PROCESSING.MAX_OBJ_PER_SAMPLE: {k} is more than the {cells} cells "
                            f"of the heatmap (POINT_CLOUD_RANGE / VOXEL_SIZE / FEATURE_MAP_STRIDE "
                            f"{head.feature_map_stride}); expected at most {cells}")



class MSSFPointPillar(_MSSFDetector, PointPillar):
    """The paper's MSSF-PP: ``PillarVFE`` + ``PointPillarScatter`` + ``MSSFBaseBEVBackbone`` (the fusion
    blocks in the first 2D blocks, :mod:`~mssf_examples.openpcdet.bev_backbone`) + ``AnchorHeadSingle``;
    the fusion settings are under ``BACKBONE_2D``. ``BACKBONE_2D.NAME: BaseBEVBackbone`` (or
    ``NUM_FUSION_BLOCKS: 0`` and no ``IMAGE_BRANCH``) is OpenPCDet's ``PointPillar``."""

    FUSION_MODULE = "backbone_2d"

    def __init__(self, model_cfg, num_class, dataset):
        PointPillar.__init__(self, model_cfg=model_cfg, num_class=num_class, dataset=dataset)
        self._add_image_branch(model_cfg, dataset)

    def build_backbone_2d(self, model_info_dict):
        """OpenPCDet's, with the grid passed to the fusion backbone (the stock call passes channels only)."""
        from .bev_backbone import MSSFBaseBEVBackbone

        cfg = self.model_cfg.get("BACKBONE_2D", None)
        if cfg is None or cfg.NAME != "MSSFBaseBEVBackbone":
            if cfg is not None and int(cfg.get("NUM_FUSION_BLOCKS", 0) or 0) > 0:  # would run without fusing
                raise MSSFError(f"MODEL.BACKBONE_2D.NAME: NUM_FUSION_BLOCKS {cfg.NUM_FUSION_BLOCKS} needs "
                                f"MSSFBaseBEVBackbone (the 2D backbone that fuses), got {cfg.NAME!r}")
            return super().build_backbone_2d(model_info_dict)
        module = MSSFBaseBEVBackbone(cfg, input_channels=model_info_dict["num_bev_features"],
                                     voxel_size=model_info_dict["voxel_size"],
                                     point_cloud_range=model_info_dict["point_cloud_range"])
        model_info_dict["module_list"].append(module)
        model_info_dict["num_bev_features"] = module.num_bev_features
        return module, model_info_dict



#: what to merge into ``pcdet.models.detectors.__all__``
MSSF_DETECTORS = {"MSSFSECONDNet": MSSFSECONDNet, "MSSFVoxelNeXt": MSSFVoxelNeXt, "MSSFCenterPoint": MSSFCenterPoint,
                  "MSSFPointPillar": MSSFPointPillar}
