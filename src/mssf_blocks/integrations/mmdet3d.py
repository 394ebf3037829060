"""mmdetection3d ``batch_inputs_dict`` + ``data_samples`` -> :class:`~mssf_blocks.samplers.FusionInputs`.

No mmdet3d import: the adapter reads plain metainfo dicts (``[s.metainfo for s in data_samples]``,
the ``batch_input_metas`` that mmdet3d's detectors pass around). What mmdet3d 1.x records:

* ``points``: a list of ``(P_i, 3 + C)`` tensors, one per sample, *augmented*.
* point augmentation (``RandomFlip3D``, ``GlobalRotScaleTrans``): ``pcd_horizontal_flip``
  (``y -> -y``), ``pcd_vertical_flip`` (``x -> -x``), ``pcd_rotation`` (the ``(3, 3)`` matrix applied as
  ``p @ pcd_rotation`` to row vectors), ``pcd_scale_factor``, ``pcd_trans``, and
  ``transformation_3d_flow``, the order they ran (``'HF'``, ``'VF'``, ``'R'``, ``'S'``, ``'T'``; stock
  KITTI configs flip then rotate, nuScenes configs rotate then flip). BEVFusion's transforms record
  the composed ``lidar_aug_matrix`` instead (``p_aug = M @ p``), which wins when present.
* cameras: ``lidar2img`` ``(4, 4)`` or ``(V, 4, 4)`` for the *original* image; image augmentation is
  either BEVFusion's ``img_aug_matrix`` ``(V, 4, 4)`` or mmcv's ``scale_factor`` ``(w, h)``,
  ``img_crop_offset`` ``(x, y)`` and ``flip`` (horizontal, of the ``img_shape`` image), applied in
  that order (as mmdet3d's ``point_sample`` does; here in exact pixel-centre form).
* ``batch_input_shape`` ``(H, W)``: the padded image tensor the features come from (padding is at the
  bottom/right, so pixel coordinates are unchanged); ``img_shape`` / ``pad_shape`` per sample.
* image features: ``extract_img_feat`` returns levels ``(B*V, C, H_l, W_l)`` (views folded into the batch).
"""

from __future__ import annotations

from typing import Any, List, Mapping, Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import FusionInputs
from mssf_blocks.geometry import apply_image_augmentation, augmentation_matrix
from mssf_blocks.checks.calibration import check_calibration_image_size
from mssf_blocks.checks.matrices import check_affine_4x4
from mssf_blocks.integrations._common import affine_4x4, as_bool, as_float64, image_levels_bv, lidar2img_3x4, pixel_affine_from_4x4

__all__ = [
    "lidar_aug_matrix",
    "image_aug_affine",
    "camera_from_meta",
    "fusion_inputs_from_mmdet3d",
    "fusion_inputs_from_data_samples",
]

_FLOW_OPS = ("HF", "VF", "R", "S", "T")
_IMAGE_AUG = ("meta", "none")


def lidar_aug_matrix(meta: Mapping) -> Tensor:
    """``(4, 4)`` float64 ``M`` with ``p_augmented = M @ p_sensor`` from one sample's metainfo.

    ``lidar_aug_matrix`` when recorded (BEVFusion), else ``transformation_3d_flow`` applied to the
    ``pcd_*`` keys; the identity when neither is there.

    Raises:
        MSSFError: ``pcd_*`` keys that move the points without a ``transformation_3d_flow`` to order
            them (add it to ``Pack3DDetInputs``' ``meta_keys``), an op listed twice (the metainfo keeps
            only its last parameters), an unknown op.
    """
    if "lidar_aug_matrix" in meta:
        return check_affine_4x4(as_float64(meta["lidar_aug_matrix"], "lidar_aug_matrix", (4, 4)), "lidar_aug_matrix")
    steps = {
        "HF": augmentation_matrix(flip_x=as_bool(meta.get("pcd_horizontal_flip", False), "pcd_horizontal_flip")),
        "VF": augmentation_matrix(flip_y=as_bool(meta.get("pcd_vertical_flip", False), "pcd_vertical_flip")),
        "S": augmentation_matrix(scale=float(as_float64(meta.get("pcd_scale_factor", 1.0), "pcd_scale_factor"))),
        "T": affine_4x4(translation=as_float64(meta.get("pcd_trans", (0.0, 0.0, 0.0)), "pcd_trans").reshape(-1)[:3]),
        # mmdet3d rotates row vectors, p' = p @ pcd_rotation, i.e. column vectors by its transpose
        "R": affine_4x4(linear=as_float64(meta.get("pcd_rotation", torch.eye(3)), "pcd_rotation", (3, 3)).T),
    }
    flow = meta.get("transformation_3d_flow")
    if flow is None:
        moved = [k for k, m in steps.items() if not torch.allclose(m, torch.eye(4, dtype=torch.float64), atol=1e-12)]
        if moved:
            raise MSSFError(
                f"meta: the pcd_* keys move the points ({moved}) but there is no transformation_3d_flow to "
                "order them; keep 'transformation_3d_flow' in Pack3DDetInputs' meta_keys"
            )
        return torch.eye(4, dtype=torch.float64)
    flow = list(flow)
    bad = [op for op in flow if op not in _FLOW_OPS]
    if bad:
        raise MSSFError(f"transformation_3d_flow: expected ops among {_FLOW_OPS}, got {bad}")
    twice = sorted({op for op in flow if flow.count(op) > 1})
    if twice:
        raise MSSFError(f"transformation_3d_flow: {twice} listed twice; the metainfo keeps only the last parameters")
    m = torch.eye(4, dtype=torch.float64)
    for op in flow:
        m = steps[op] @ m
    return m


def _scale_factor(meta: Mapping) -> Tuple[float, float]:
    sf = as_float64(meta.get("scale_factor", 1.0), "scale_factor").reshape(-1)
    if sf.numel() == 1:
        return float(sf), float(sf)
    if sf.numel() not in (2, 4):  # mmcv: (w, h) or (w, h, w, h); per-view lists are not supported
        raise MSSFError(f"scale_factor: expected a number, (w, h) or (w, h, w, h), got {sf.numel()} values")
    return float(sf[0]), float(sf[1])


def image_aug_affine(meta: Mapping, num_cameras: int) -> Tensor:
    """``(V, 3, 3)`` float64 pixel affine ``A`` of the image augmentation (``lidar2img' = A @ lidar2img``).

    ``img_aug_matrix`` as recorded when present; otherwise mmcv's resize (``scale_factor``), crop
    (``img_crop_offset``) and horizontal ``flip`` in exact pixel-centre form, the convention of
    :func:`~mssf_blocks.geometry.image_augmentation_matrix` (pixel ``i``'s centre at ``i``: resize
    ``u -> (u + 0.5) * s - 0.5``, crop ``u -> u - x0``, flip ``u -> W - 1 - u`` with ``W`` from
    ``img_shape``), written with the recorded scale factors (mmcv records those, not the sizes). mmdet3d's ``point_sample`` uses ``u * s`` and ``W - u`` instead: up to half a
    pixel (resize) and one pixel (flip) from where the resized / flipped image content lies.
    """
    if "img_aug_matrix" in meta:
        aug = as_float64(meta["img_aug_matrix"], "img_aug_matrix")
        aug = aug.expand(num_cameras, 4, 4) if aug.shape == (4, 4) else aug
        if aug.shape != (num_cameras, 4, 4):
            raise MSSFError(f"img_aug_matrix: expected (4, 4) or (V={num_cameras}, 4, 4), got {tuple(aug.shape)}")
        return pixel_affine_from_4x4(aug, "img_aug_matrix")
    sx, sy = _scale_factor(meta)
    a = torch.tensor([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    if "img_crop_offset" in meta:
        ox, oy = as_float64(meta["img_crop_offset"], "img_crop_offset", (2,)).tolist()
        a = torch.tensor([[1.0, 0.0, -ox], [0.0, 1.0, -oy], [0.0, 0.0, 1.0]], dtype=torch.float64) @ a
    if as_bool(meta.get("flip", False), "flip"):
        direction = meta.get("flip_direction", "horizontal")
        if direction != "horizontal":
            raise MSSFError(f"flip_direction: only 'horizontal' image flips are supported, got {direction!r}")
        if "img_shape" not in meta:
            raise MSSFError("meta: a flipped image needs img_shape (H, W) to mirror the u axis")
        w = float(as_float64(meta["img_shape"], "img_shape").reshape(-1)[1])
        a = torch.tensor([[-1.0, 0.0, w - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64) @ a
    if num_cameras > 1 and not torch.equal(a, torch.eye(3, dtype=torch.float64)):
        # mmcv's keys describe one image; per-view augmentation must come as a matrix per view
        raise MSSFError(
            f"meta: image augmentation keys (scale_factor / img_crop_offset / flip) with {num_cameras} cameras; "
            "record it per view as img_aug_matrix (V, 4, 4), or fold it into lidar2img and pass image_aug='none'"
        )
    return a.expand(num_cameras, 3, 3)


def camera_from_meta(meta: Mapping, image_aug: str = "meta") -> Tensor:
    """``(V, 3, 4)`` float64 ``lidar2img`` of the augmented image(s) of one sample.

    Args:
        meta: one sample's metainfo.
        image_aug: ``"meta"`` folds in :func:`image_aug_affine`; ``"none"`` takes ``lidar2img`` as
            already describing the augmented image (pipelines that update it themselves).

    Warns (:class:`~mssf_blocks.errors.MSSFGeometryWarning`) when ``lidar2img``'s principal point lies 1.2 x
    or more (or 1 / 1.2 or less) off the centre of the image it describes (``ori_shape``, with ``"none"``
    ``img_shape``) on both axes: images resized on disk while the calibration was kept (``_calibration``).
    """
    if image_aug not in _IMAGE_AUG:
        raise MSSFError(f"image_aug: expected one of {_IMAGE_AUG}, got {image_aug!r}")
    if "lidar2img" not in meta:
        raise MSSFError(f"meta: expected 'lidar2img' ((4, 4) or (V, 4, 4)), got keys {sorted(meta)}")
    l2i = lidar2img_3x4(as_float64(meta["lidar2img"], "lidar2img"), "lidar2img")
    if l2i.dim() == 2:
        l2i = l2i[None]
    if l2i.dim() != 3:
        raise MSSFError(f"lidar2img: expected (4, 4) or (V, 4, 4), got {tuple(l2i.shape)}")
    # lidar2img describes the loaded image (ori_shape), or with image_aug="none" the augmented one (img_shape)
    key = "ori_shape" if image_aug == "meta" else "img_shape"
    if meta.get(key) is not None:
        hw = as_float64(meta[key], key)
        if hw.dim() in (1, 2) and hw.shape[-1] in (2, 3):  # (H, W[, C]), or one per camera
            where = f"{key} {tuple(int(v) for v in hw.reshape(-1)[:2])}"
            check_calibration_image_size(l2i, hw[..., :2], "lidar2img", where)
    if image_aug == "meta":
        l2i = apply_image_augmentation(l2i[None], image_aug_affine(meta, l2i.shape[0])[None])[0]
    return l2i


def _image_size(metas: Sequence[Mapping]) -> Tuple[int, int]:
    for key in ("batch_input_shape", "pad_shape", "img_shape"):
        if all(key in m for m in metas):
            sizes = {tuple(int(s) for s in as_float64(m[key], key).reshape(-1)[:2].tolist()) for m in metas}
            if len(sizes) != 1:
                raise MSSFError(f"{key}: expected one image tensor size for the batch, got {sorted(sizes)}")
            return sizes.pop()
    raise MSSFError("batch_input_metas: expected batch_input_shape (set by Det3DDataPreprocessor); pass image_size=(H, W)")


def fusion_inputs_from_mmdet3d(
    points: Sequence[Tensor],
    img_feats: Sequence[Tensor],
    batch_input_metas: Sequence[Mapping],
    image_aug: str = "meta",
    image_size: Optional[Tuple[int, int]] = None,
) -> FusionInputs:
    """The :class:`FusionInputs` of an mmdet3d batch.

    Args:
        points: per sample ``(P_i, 3 + C)`` augmented points (``batch_inputs_dict['points']``).
        img_feats: image levels ``(B*V, C, H, W)`` / ``(B, C, H, W)`` / ``(B, V, C, H, W)``
            (``extract_img_feat``'s output).
        batch_input_metas: per sample metainfo dicts (``[s.metainfo for s in batch_data_samples]``).
        image_aug: see :func:`camera_from_meta`.
        image_size: ``(H, W)`` the features were computed from; default ``batch_input_shape``.
    """
    if isinstance(points, Tensor) or not isinstance(points, (list, tuple)):
        raise MSSFError(f"points: expected a list of (P_i, 3 + C) tensors (one per sample), got {type(points).__name__}")
    metas = list(batch_input_metas)
    if len(metas) != len(points) or not metas:
        # (which one is short is not known here: both are named; the middle encoder decides by its batch_size)
        raise MSSFError(f"batch_input_metas, points: expected one metainfo dict and one point tensor per sample, got "
                        f"{len(metas)} metainfo dict(s) and {len(points)} point tensor(s)")
    for i, p in enumerate(points):
        if not isinstance(p, Tensor) or p.dim() != 2 or p.shape[1] < 3 or not p.is_floating_point():
            raise MSSFError(f"points[{i}]: expected a floating (P, 3 + C) tensor, got {getattr(p, 'shape', type(p).__name__)}")
    cams = [camera_from_meta(m, image_aug) for m in metas]
    if len({c.shape[0] for c in cams}) != 1:
        raise MSSFError(f"lidar2img: expected the same number of cameras in every sample, got {[c.shape[0] for c in cams]}")
    l2i = torch.stack(cams)
    m = torch.stack([lidar_aug_matrix(meta) for meta in metas])
    flat = torch.cat(list(points), 0)
    dev, dt = flat.device, flat.dtype
    batch = torch.cat([torch.full((p.shape[0],), i, dtype=torch.long, device=dev) for i, p in enumerate(points)])
    levels = image_levels_bv(list(img_feats), len(metas), l2i.shape[1], "img_feats")
    eye = torch.eye(4, dtype=torch.float64)
    p2s = None if all(torch.equal(mi, eye) for mi in m) else torch.linalg.inv(m).to(dev, dt)
    size = _image_size(metas) if image_size is None else image_size
    return FusionInputs(levels, l2i.to(dev, dt), size, flat[:, :3], batch, p2s)  # (P, 3): x, y, z only


def fusion_inputs_from_data_samples(
    batch_inputs_dict: Mapping, batch_data_samples: Sequence[Any], img_feats: Sequence[Tensor], **kwargs: Any
) -> FusionInputs:
    """:func:`fusion_inputs_from_mmdet3d` from ``batch_inputs_dict['points']`` and ``Det3DDataSample`` s."""
    if "points" not in batch_inputs_dict:
        raise MSSFError(f"batch_inputs_dict: expected 'points', got keys {sorted(batch_inputs_dict)}")
    metas: List[Mapping] = []
    for i, s in enumerate(batch_data_samples):
        if not hasattr(s, "metainfo"):
            raise MSSFError(f"batch_data_samples[{i}]: expected a Det3DDataSample (with .metainfo), got {type(s).__name__}")
        metas.append(s.metainfo)
    return fusion_inputs_from_mmdet3d(batch_inputs_dict["points"], img_feats, metas, **kwargs)
