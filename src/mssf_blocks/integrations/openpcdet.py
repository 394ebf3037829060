"""OpenPCDet ``batch_dict`` -> :class:`~mssf_blocks.samplers.FusionInputs` (no OpenPCDet import).

What an OpenPCDet batch holds (``DatasetTemplate.collate_batch`` then ``load_data_to_gpu``):

* ``points (P, 1 + 3 + C)``: the batch index in column 0, then the *augmented* ``x, y, z`` and features;
  ``batch_size``.
* point augmentation, as recorded by ``DataAugmentor`` (one entry per sample after collation):
  ``flip_x`` (``random_flip_along_x``: ``y -> -y``), ``flip_y`` (``x -> -x``), ``noise_rot`` (rotation
  about z, counter-clockwise, ``x -> y``), ``noise_scale``, ``noise_translate`` ``(B, 1, 3)``. They are
  applied in the order of ``DATA_AUGMENTOR.AUG_CONFIG_LIST`` (:func:`augmentor_order`); the default is
  OpenPCDet's usual flip -> rotation -> scaling -> translation.
* cameras, KITTI style (``GET_ITEM_LIST: [points, images, calib_matricies]``): ``images (B, 3, H, W)``
  (padded at the bottom/right to the largest image; ``(B, H, W, 3)`` numpy before
  ``load_data_to_gpu``), ``trans_lidar_to_cam (B, 4, 4)`` (``R0 @ V2C``), ``trans_cam_to_img (B, 3, 4)``
  (``P2``), ``image_shape (B, 2)`` (each unpadded ``(H, W)``);
* or nuScenes/BEVFusion style: ``camera_imgs (B, V, 3, H, W)``, ``lidar2image (B, V, 4, 4)`` and
  ``img_aug_matrix (B, V, 4, 4)`` (the resize/crop/flip/rotate of every view, ``image_calibrate``).
* image features: whatever module ran before the 3D backbone; OpenPCDet's BEVFusion neck writes
  ``image_fpn``, a tuple of ``(B*V, C, H_l, W_l)`` levels.

``lidar_aug_matrix`` (``DatasetTemplate.set_lidar_aug_matrix``) is used only when none of the
individual keys is present: it always applies flip -> rotation -> scaling -> translation, and it
records no flip at all when ``ALONG_AXIS_LIST`` has no ``'y'`` (it tests for the ``flip_y`` key), the
usual KITTI/VoD setting.
"""

from __future__ import annotations

from typing import Any, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.matrices import check_affine_4x4
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import FusionInputs
from mssf_blocks.geometry import apply_image_augmentation, augmentation_matrix
from mssf_blocks.integrations._common import (
    as_bool,
    as_float64,
    image_levels_bv,
    lidar2img_3x4,
    pixel_affine_from_4x4,
    points_with_batch,
)

__all__ = [
    "DEFAULT_AUGMENTOR_ORDER",
    "augmentor_order",
    "lidar_aug_matrices",
    "camera_from_batch_dict",
    "fusion_inputs_from_batch_dict",
]

#: OpenPCDet's world augmentors that move the point cloud, in the order of its stock configs.
DEFAULT_AUGMENTOR_ORDER = ("random_world_flip", "random_world_rotation", "random_world_scaling", "random_world_translation")
_WORLD_KEYS = {
    "random_world_flip": ("flip_x", "flip_y"),
    "random_world_rotation": ("noise_rot",),
    "random_world_scaling": ("noise_scale",),
    "random_world_translation": ("noise_translate",),
}
# Augmentors that change the image content without recording it: nothing can undo them.
_UNRECORDED_IMAGE_AUGMENTORS = ("random_image_flip",)


def _get(cfg: Any, key: str, default: Any = None) -> Any:
    if isinstance(cfg, Mapping):
        return cfg.get(key, default)
    return getattr(cfg, key, default)


def augmentor_order(data_augmentor_cfg: Any) -> Tuple[str, ...]:
    """The world augmentors of ``DATA_CONFIG.DATA_AUGMENTOR`` in the order ``DataAugmentor`` runs them.

    Args:
        data_augmentor_cfg: the ``DATA_AUGMENTOR`` dict/EasyDict (``AUG_CONFIG_LIST`` of ``{NAME: ...}``
            entries, optional ``DISABLE_AUG_LIST``).

    Returns:
        the names among :data:`DEFAULT_AUGMENTOR_ORDER` that are enabled, in config order (object-level
        augmentors such as ``gt_sampling`` do not move the frame and are left out).

    Raises:
        MSSFError: the config enables ``random_image_flip``, which flips the image without recording it.
    """
    entries = _get(data_augmentor_cfg, "AUG_CONFIG_LIST")
    if not isinstance(entries, (list, tuple)):
        raise MSSFError(f"data_augmentor_cfg: expected a DATA_AUGMENTOR config with an AUG_CONFIG_LIST list, got {entries!r}")
    disabled = set(_get(data_augmentor_cfg, "DISABLE_AUG_LIST", None) or ())
    names = []
    for entry in entries:
        name = _get(entry, "NAME")
        if name in disabled:
            continue
        if name in _UNRECORDED_IMAGE_AUGMENTORS:
            raise MSSFError(
                f"data_augmentor_cfg: {name} flips the image but records nothing, so the projection cannot "
                "follow it; disable it (DISABLE_AUG_LIST) for camera fusion"
            )
        if name in _WORLD_KEYS:
            names.append(name)
    return tuple(names)


def _per_sample(batch_dict: Mapping, key: str, batch_size: int, width: int) -> Tensor:
    t = as_float64(batch_dict[key], key)
    t = t.reshape(batch_size, -1) if t.numel() == batch_size * width else None
    if t is None:
        raise MSSFError(
            f"{key}: expected {width} value(s) per sample for batch_size={batch_size}, "
            f"got shape {tuple(as_float64(batch_dict[key], key).shape)}"
        )
    return t


def lidar_aug_matrices(batch_dict: Mapping, order: Optional[Sequence[str]] = None) -> Optional[Tensor]:
    """``(B, 4, 4)`` float64 ``M`` with ``p_augmented = M @ p_sensor``, from the recorded keys.

    Args:
        batch_dict: a collated OpenPCDet batch.
        order: world augmentor names in the order they ran (:func:`augmentor_order`); default
            :data:`DEFAULT_AUGMENTOR_ORDER`.

    Returns:
        ``None`` when the batch records no augmentation (evaluation batches).
    """
    order = DEFAULT_AUGMENTOR_ORDER if order is None else tuple(order)
    unknown = [n for n in order if n not in _WORLD_KEYS]
    if unknown:
        raise MSSFError(f"order: expected names among {DEFAULT_AUGMENTOR_ORDER}, got {unknown}")
    b = int(batch_dict["batch_size"])
    keys = [k for ks in _WORLD_KEYS.values() for k in ks if k in batch_dict]
    if not keys:
        if "lidar_aug_matrix" in batch_dict:
            return check_affine_4x4(as_float64(batch_dict["lidar_aug_matrix"], "lidar_aug_matrix", (b, 4, 4)),
                                    "lidar_aug_matrix")
        return None
    missing = [n for n in _WORLD_KEYS if any(k in batch_dict for k in _WORLD_KEYS[n]) and n not in order]
    if missing:
        raise MSSFError(f"order: the batch records {missing} but order {order} does not list them")
    flips = {k: _per_sample(batch_dict, k, b, 1)[:, 0] for k in ("flip_x", "flip_y") if k in batch_dict}
    rot = _per_sample(batch_dict, "noise_rot", b, 1)[:, 0] if "noise_rot" in batch_dict else None
    scale = _per_sample(batch_dict, "noise_scale", b, 1)[:, 0] if "noise_scale" in batch_dict else None
    trans = _per_sample(batch_dict, "noise_translate", b, 3) if "noise_translate" in batch_dict else None
    out = []
    for i in range(b):
        m = torch.eye(4, dtype=torch.float64)
        for name in order:
            if name == "random_world_flip" and flips:
                fx = as_bool(flips["flip_x"][i], "flip_x") if "flip_x" in flips else False
                fy = as_bool(flips["flip_y"][i], "flip_y") if "flip_y" in flips else False
                step = augmentation_matrix(flip_x=fx, flip_y=fy)
            elif name == "random_world_rotation" and rot is not None:
                step = augmentation_matrix(rotation=float(rot[i]))
            elif name == "random_world_scaling" and scale is not None:
                step = augmentation_matrix(scale=float(scale[i]))
            elif name == "random_world_translation" and trans is not None:
                step = augmentation_matrix(translation=trans[i].tolist())
            else:
                continue
            m = step @ m
        out.append(m)
    return torch.stack(out)


def _image_size(batch_dict: Mapping) -> Tuple[int, int]:
    if "camera_imgs" in batch_dict:
        return tuple(int(s) for s in batch_dict["camera_imgs"].shape[-2:])
    if "images" in batch_dict:
        img = batch_dict["images"]
        # before load_data_to_gpu the images are numpy (B, H, W, 3), after it tensors (B, 3, H, W)
        return tuple(int(s) for s in (img.shape[1:3] if not isinstance(img, Tensor) else img.shape[-2:]))
    if "image_shape" in batch_dict:
        # collate_batch pads every image at the bottom/right to the largest one
        shape = as_float64(batch_dict["image_shape"], "image_shape", (None, 2))
        return int(shape[:, 0].max()), int(shape[:, 1].max())
    raise MSSFError("batch_dict: expected camera_imgs, images or image_shape to give the image size; pass image_size=(H, W)")


def camera_from_batch_dict(batch_dict: Mapping) -> Tuple[Tensor, Tuple[int, int]]:
    """``(lidar2img (B, V, 3, 4) float64, image_size (H, W))`` from the batch's camera keys.

    ``lidar2image`` (+ ``img_aug_matrix``) when present, otherwise ``trans_cam_to_img @
    trans_lidar_to_cam`` (one camera; + ``img_aug_matrix`` ``(B, 1, 4, 4)`` when present, e.g. the examples'
    image branch's resize). ``image_size`` is that of the (padded) image tensor.
    """
    b = int(batch_dict["batch_size"])
    if "lidar2image" in batch_dict:
        l2i = lidar2img_3x4(as_float64(batch_dict["lidar2image"], "lidar2image", (b, None, None, 4)), "lidar2image")
        if "img_aug_matrix" in batch_dict:
            aug = as_float64(batch_dict["img_aug_matrix"], "img_aug_matrix", (b, l2i.shape[1], 4, 4))
            l2i = apply_image_augmentation(l2i, pixel_affine_from_4x4(aug, "img_aug_matrix"))
    elif "trans_lidar_to_cam" in batch_dict and "trans_cam_to_img" in batch_dict:
        l2c = as_float64(batch_dict["trans_lidar_to_cam"], "trans_lidar_to_cam", (b, 4, 4))
        c2i = as_float64(batch_dict["trans_cam_to_img"], "trans_cam_to_img", (b, 3, 4))
        l2i = (c2i @ l2c)[:, None]
        if "img_aug_matrix" in batch_dict:  # e.g. the image branch's IMAGE_SIZE resize (one camera)
            aug = as_float64(batch_dict["img_aug_matrix"], "img_aug_matrix", (b, 1, 4, 4))
            l2i = apply_image_augmentation(l2i, pixel_affine_from_4x4(aug, "img_aug_matrix"))
    else:
        raise MSSFError(
            "batch_dict: expected camera matrices, lidar2image (BEVFusion/nuScenes) or trans_lidar_to_cam + "
            "trans_cam_to_img (KITTI, GET_ITEM_LIST 'calib_matricies'); got keys " + str(sorted(batch_dict))
        )
    return l2i, _image_size(batch_dict)


def fusion_inputs_from_batch_dict(
    batch_dict: Mapping,
    image_features: Optional[Sequence[Tensor]] = None,
    image_features_key: str = "image_fpn",
    order: Optional[Sequence[str]] = None,
    image_size: Optional[Tuple[int, int]] = None,
) -> FusionInputs:
    """The :class:`FusionInputs` of an OpenPCDet batch.

    Args:
        batch_dict: the collated batch (after ``load_data_to_gpu``, or numpy before it).
        image_features: image levels ``(B, C, H, W)``, ``(B*V, C, H, W)`` or ``(B, V, C, H, W)``;
            default ``batch_dict[image_features_key]``.
        image_features_key: where the image branch put its levels (OpenPCDet's BEVFusion neck:
            ``"image_fpn"``).
        order: the world augmentors in the order they ran (:func:`augmentor_order` of
            ``DATA_CONFIG.DATA_AUGMENTOR``); default flip -> rotation -> scaling -> translation.
        image_size: ``(H, W)`` of the image the features were computed from; default the batch's
            (padded) image tensor size.

    Returns:
        :class:`FusionInputs` with the raw augmented x, y, z, ``lidar2img`` (image augmentation
        folded in) and ``points_to_sensor`` (the inverse point augmentation, ``None`` when none is
        recorded), in the points' dtype and device.
    """
    if not isinstance(batch_dict, Mapping) or "points" not in batch_dict or "batch_size" not in batch_dict:
        raise MSSFError("batch_dict: expected an OpenPCDet batch with 'points' and 'batch_size'")
    points, points_batch = points_with_batch(batch_dict["points"], "batch_dict['points']")
    b = int(batch_dict["batch_size"])
    if image_features is None:
        if image_features_key not in batch_dict:
            raise MSSFError(
                f"image_features: not given and batch_dict has no {image_features_key!r}; run the image "
                "branch before the 3D backbone (module_topology) or pass image_features"
            )
        image_features = batch_dict[image_features_key]
    l2i, size = camera_from_batch_dict(batch_dict)
    levels = image_levels_bv(list(image_features), b, l2i.shape[1], "image_features")
    m = lidar_aug_matrices(batch_dict, order)
    dev, dt = points.device, points.dtype
    p2s = None if m is None else torch.linalg.inv(m).to(dev, dt)
    return FusionInputs(levels, l2i.to(dev, dt), size if image_size is None else image_size, points[:, :3], points_batch,
                        p2s)
