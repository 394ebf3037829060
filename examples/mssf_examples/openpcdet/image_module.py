"""The image branch of the OpenPCDet MSSF detectors: ResNet + FPN (:mod:`mssf_examples.models.image_branch`,
no torchvision) as an OpenPCDet module that reads ``batch_dict['images']`` and writes the FPN levels.

Model config (``MODEL.IMAGE_BRANCH``)::

    IMAGE_BRANCH:
        DEPTH: 50                 # ResNet depth
        FPN_CHANNELS: 256
        NUM_OUTS: 4               # FPN levels (strides 4, 8, 16, 32)
        FROZEN: True              # the paper: pre-trained and frozen
        CHECKPOINT: /path/htc_resnet50_fpn.pth    # required when FROZEN
        CHECKPOINT_PREFIXES: {'img_backbone.': 'backbone.', 'img_neck.': 'neck.'}
        MEAN: [0.485, 0.456, 0.406]   # on [0, 1] RGB, as OpenPCDet's KittiDataset loads images
        STD: [0.229, 0.224, 0.225]
        OUTPUT_KEY: image_fpn     # = BACKBONE_3D.IMAGE_FEATURES_KEY
        IMAGE_SIZE: [608, 968]    # optional (H, W) the branch resizes the images to (default: as loaded)

OpenPCDet's KITTI-style datasets have no image resize: a VoD frame reaches the model at 1216 x 1936. With
``IMAGE_SIZE`` the branch resizes ``batch_dict['images']`` (bilinear, antialiased, edges aligned: the image
tensor is replaced) and records the resize as BEVFusion's ``img_aug_matrix`` ``(B, 1, 4, 4)`` (composed with
one already there), which the fusion blocks apply to ``trans_cam_to_img @ trans_lidar_to_cam`` in exact
pixel-centre form (:func:`mssf_blocks.geometry.image_augmentation_matrix`). Boxes and evaluation keep the
calibration files: only the image the network sees changes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, Mapping

import torch
import torch.nn.functional as F
from torch import nn

from mssf_blocks.checks.arguments import check_image_size
from mssf_blocks.errors import MSSFError
from mssf_blocks.geometry import image_augmentation_matrix

from ..models.image_branch import ImageBranch

__all__ = ["OpenPCDetImageBranch", "IMAGE_BRANCH_DEFAULTS", "load_branch_checkpoint", "expect_trained_checkpoint"]

#: set by :func:`expect_trained_checkpoint`: the branch's weights will come from a trained detector checkpoint
_FROM_TRAINED_CHECKPOINT = False


def expect_trained_checkpoint(expected: bool = True) -> None:
    """Say that the detectors built from now on get their weights from a trained checkpoint (OpenPCDet's
    ``test.py``, ``train.py --ckpt``): a ``MODEL.IMAGE_BRANCH.CHECKPOINT`` file that is not there is then not
    needed. The branch refuses to run until a checkpoint holding all its weights has been loaded (the
    detector checks each ``load_params_from_file`` / ``load_params_with_optimizer``).
    ``python -m mssf_examples.openpcdet`` calls it for ``test.py`` and for ``train.py --ckpt``."""
    global _FROM_TRAINED_CHECKPOINT
    _FROM_TRAINED_CHECKPOINT = bool(expected)

IMAGE_BRANCH_DEFAULTS: Dict[str, Any] = {
    "DEPTH": 50, "BASE_CHANNELS": 64, "FPN_CHANNELS": 256, "NUM_OUTS": 4, "FROZEN": True, "CHECKPOINT": None,
    "CHECKPOINT_PREFIXES": {"img_backbone.": "backbone.", "img_neck.": "neck."},
    "MEAN": [0.485, 0.456, 0.406], "STD": [0.229, 0.224, 0.225], "OUTPUT_KEY": "image_fpn", "IMAGE_SIZE": None,
}


def load_branch_checkpoint(branch: nn.Module, path: Any, prefixes: Mapping[str, str]) -> None:
    """Load ``backbone.*`` / ``neck.*`` weights from a checkpoint file (a state dict, or a dict with
    ``state_dict`` / ``model_state``); keys starting with a ``prefixes`` key are renamed first."""
    path = Path(str(path)).expanduser()
    if not path.is_file():
        raise MSSFError(f"MODEL.IMAGE_BRANCH.CHECKPOINT: file not found: {path}")
    obj = torch.load(path, map_location="cpu", weights_only=True)
    state = obj.get("state_dict", obj.get("model_state", obj)) if isinstance(obj, Mapping) else None
    if not isinstance(state, Mapping):
        raise MSSFError(f"MODEL.IMAGE_BRANCH.CHECKPOINT: expected a state dict in {path}, got {type(obj).__name__}")
    renamed = {}
    for key, value in state.items():
        for old, new in prefixes.items():
            if key.startswith(old):
                key = new + key[len(old):]
                break
        if key.startswith(("backbone.", "neck.")):
            renamed[key] = value
    own = branch.state_dict()
    missing = sorted(set(own) - set(renamed))
    unexpected = sorted(set(renamed) - set(own))
    shapes = [f"{k} {tuple(renamed[k].shape)} (branch: {tuple(own[k].shape)})" for k in sorted(set(own) & set(renamed))
              if tuple(renamed[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or shapes:
        raise MSSFError(f"MODEL.IMAGE_BRANCH.CHECKPOINT: {path} does not fit the image branch (DEPTH, BASE_CHANNELS, "
                        f"FPN_CHANNELS, NUM_OUTS): missing {missing[:6]} ({len(missing)}), unexpected {unexpected[:6]} "
                        f"({len(unexpected)}), other shapes {shapes[:3]} ({len(shapes)})")
    branch.load_state_dict(renamed, strict=True)


class OpenPCDetImageBranch(nn.Module):
    """``batch_dict['images'] (B, 3, H, W)`` in [0, 1] -> ``batch_dict[OUTPUT_KEY]``: ``NUM_OUTS`` levels
    ``(B, FPN_CHANNELS, H / s, W / s)``, ``s = 4, 8, 16, 32``."""

    def __init__(self, model_cfg: Mapping[str, Any]) -> None:
        super().__init__()
        unknown = sorted(set(model_cfg) - set(IMAGE_BRANCH_DEFAULTS))
        if unknown:
            raise MSSFError(f"MODEL.IMAGE_BRANCH: unknown keys {unknown}; expected among {sorted(IMAGE_BRANCH_DEFAULTS)}")
        cfg = {**IMAGE_BRANCH_DEFAULTS, **dict(model_cfg)}
        self.cfg = cfg
        self.output_key = str(cfg["OUTPUT_KEY"])
        self.image_size = None if cfg["IMAGE_SIZE"] is None else \
            check_image_size(cfg["IMAGE_SIZE"], name="MODEL.IMAGE_BRANCH.IMAGE_SIZE")
        self.branch = ImageBranch(depth=int(cfg["DEPTH"]), base_channels=int(cfg["BASE_CHANNELS"]),
                                  fpn_channels=int(cfg["FPN_CHANNELS"]), num_outs=int(cfg["NUM_OUTS"]),
                                  frozen=bool(cfg["FROZEN"]), channels_last=False)
        #: True until a trained detector checkpoint has filled the branch (expect_trained_checkpoint)
        self.awaiting_checkpoint = False
        ckpt = cfg["CHECKPOINT"]
        if _FROM_TRAINED_CHECKPOINT and (ckpt is None or not Path(str(ckpt)).expanduser().is_file()):
            self.awaiting_checkpoint = True  # the trained checkpoint holds the branch: its source file is not needed
        elif ckpt is not None:
            load_branch_checkpoint(self.branch, ckpt, dict(cfg["CHECKPOINT_PREFIXES"]))
        elif cfg["FROZEN"]:
            raise MSSFError("MODEL.IMAGE_BRANCH.CHECKPOINT: a frozen image branch needs pre-trained weights (the paper: "
                            "HTC's ResNet-50 + FPN); got none. Set CHECKPOINT, or FROZEN: False to train it")
        self.register_buffer("mean", torch.tensor(cfg["MEAN"], dtype=torch.float32).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(cfg["STD"], dtype=torch.float32).view(1, 3, 1, 1), persistent=False)

    def _resize(self, batch_dict: Dict[str, Any], images: torch.Tensor) -> torch.Tensor:
        """``IMAGE_SIZE``: the resized images (written back to the batch) and their ``img_aug_matrix``. The batch's
        images are padded at the bottom / right to the largest: one factor per axis for all, exact for each."""
        a, _ = image_augmentation_matrix(tuple(images.shape[-2:]), resize=self.image_size)
        m = torch.eye(4, dtype=torch.float64)
        m[:2, :2], m[:2, 3] = a[:2, :2], a[:2, 2]
        b = images.shape[0]
        prev = batch_dict.get("img_aug_matrix", None)
        if prev is not None:
            m = m @ torch.as_tensor(prev, dtype=torch.float64).cpu()  # after the augmentation already recorded
        else:
            m = m.expand(b, 1, 4, 4)
        batch_dict["img_aug_matrix"] = m.to(images.device)
        resized = F.interpolate(images, size=self.image_size, mode="bilinear", align_corners=False, antialias=True)
        batch_dict["images"] = resized
        return resized

    @property
    def level_channels(self) -> list:
        return [int(self.cfg["FPN_CHANNELS"])] * int(self.cfg["NUM_OUTS"])

    def forward(self, batch_dict: Dict[str, Any]) -> Dict[str, Any]:
        if self.awaiting_checkpoint:
            raise MSSFError("MODEL.IMAGE_BRANCH: its weights were to come from a trained detector checkpoint (test.py, "
                            "train.py --ckpt), and none holding them has been loaded; load one (load_params_from_file) "
                            f"or give CHECKPOINT a file that exists (now {self.cfg['CHECKPOINT']!r})")
        images = batch_dict.get("images", None)
        if not torch.is_tensor(images) or images.dim() != 4 or images.shape[1] != 3:
            raise MSSFError("batch_dict['images']: expected (B, 3, H, W) (DATA_CONFIG.GET_ITEM_LIST with 'images'), "
                            f"got {getattr(images, 'shape', type(images).__name__)}")
        if self.image_size is not None and tuple(images.shape[-2:]) != self.image_size:
            images = self._resize(batch_dict, images)
        x = (images - self.mean) / self.std
        levels = self.branch(x.unsqueeze(1))  # (B, 1, C, h, w) per level
        batch_dict[self.output_key] = tuple(lvl[:, 0] for lvl in levels)
        return batch_dict
