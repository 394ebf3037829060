"""Shared pieces of the framework adapters: arrays to tensors, augmentation matrices, image levels.

Framework batches mix numpy arrays, Python scalars and tensors (OpenPCDet converts most keys to
tensors in ``load_data_to_gpu``, mmdet3d keeps metainfo as numpy). Matrix arithmetic here runs in
float64 on the CPU; the results are moved to the points' device and dtype at the end.
"""

from __future__ import annotations

from typing import Any, List, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

__all__: List[str] = []  # private helpers; the public adapters live in openpcdet.py / mmdet3d.py


def as_float64(value: Any, name: str, shape: Optional[Sequence[Optional[int]]] = None) -> Tensor:
    """``value`` (tensor, numpy array, list, scalar) as a CPU float64 tensor, optionally shape-checked.

    ``shape`` entries are sizes or ``None`` (any size); a mismatch raises :class:`MSSFError` naming
    ``name``.
    """
    try:
        if isinstance(value, Tensor):
            t = value.detach().to("cpu", torch.float64)
        else:
            t = torch.as_tensor(np.asarray(value, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise MSSFError(f"{name}: expected numbers (a tensor, array or list), got {type(value).__name__}: {exc}") from None
    if shape is not None:
        ok = t.dim() == len(shape) and all(s is None or s == n for s, n in zip(shape, t.shape))
        if not ok:
            spec = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
            raise MSSFError(f"{name}: expected shape {spec}, got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise MSSFError(f"{name}: expected finite values, got {t.tolist()}")
    return t


def as_bool(value: Any, name: str) -> bool:
    """A recorded flag (``True``, ``np.bool_``, ``1.0`` after OpenPCDet's float conversion) as bool."""
    t = as_float64(value, name)
    if t.numel() != 1 or float(t) not in (0.0, 1.0):
        raise MSSFError(f"{name}: expected one boolean flag, got {value!r}")
    return bool(float(t))


def affine_4x4(linear: Optional[Tensor] = None, translation: Optional[Tensor] = None) -> Tensor:
    """``(4, 4)`` float64 ``[[linear, translation], [0, 0, 0, 1]]``."""
    m = torch.eye(4, dtype=torch.float64)
    if linear is not None:
        m[:3, :3] = linear
    if translation is not None:
        m[:3, 3] = translation
    return m


def pixel_affine_from_4x4(m: Tensor, name: str) -> Tensor:
    """The ``(..., 3, 3)`` pixel affine of a BEVFusion-style ``(..., 4, 4)`` image augmentation.

    BEVFusion (OpenPCDet's ``image_calibrate`` and mmdet3d's ``ImageAug3D``) stores the 2-D
    resize/crop/flip/rotate as ``m[:2, :2]`` (linear) and ``m[:2, 3]`` (translation), applied to the
    pixel ``(u, v)`` after the perspective division; as a 3 x 3 affine it acts on ``(u*d, v*d, d)``.
    """
    if m.shape[-2:] != (4, 4):
        raise MSSFError(f"{name}: expected (..., 4, 4) matrices, got shape {tuple(m.shape)}")
    a = torch.zeros(m.shape[:-2] + (3, 3), dtype=m.dtype)
    a[..., :2, :2] = m[..., :2, :2]
    a[..., :2, 2] = m[..., :2, 3]
    a[..., 2, 2] = 1.0
    if not torch.allclose(m[..., 2, :], torch.tensor([0.0, 0.0, 1.0, 0.0], dtype=m.dtype).expand_as(m[..., 2, :]),
                          atol=1e-9):
        raise MSSFError(f"{name}: expected a pixel-plane augmentation (third row (0, 0, 1, 0)), got {m[..., 2, :].tolist()}")
    return a


def lidar2img_3x4(m: Tensor, name: str) -> Tensor:
    """``(..., 3, 4)`` or ``(..., 4, 4)`` projection matrices as ``(..., 3, 4)``."""
    if m.dim() < 2 or m.shape[-1] != 4 or m.shape[-2] not in (3, 4):
        raise MSSFError(f"{name}: expected (..., 3, 4) or (..., 4, 4) matrices, got shape {tuple(m.shape)}")
    return m[..., :3, :]


def points_with_batch(points: Tensor, name: str) -> tuple:
    """OpenPCDet-style ``(P, 1 + 3 + C)`` points (batch index first) -> ``(points (P, 3+C), batch (P,))``."""
    if not isinstance(points, Tensor):
        points = torch.as_tensor(np.asarray(points))
    if points.dim() != 2 or points.shape[1] < 4:
        raise MSSFError(f"{name}: expected (P, 1 + 3 + C) points with the batch index first, got shape {tuple(points.shape)}")
    if not points.is_floating_point():
        raise MSSFError(f"{name}: expected floating-point points, got dtype {points.dtype}")
    batch = points[:, 0]
    if points.shape[0] and not bool((batch == batch.round()).all() and (batch >= 0).all()):
        raise MSSFError(f"{name}: column 0 must hold non-negative integer batch indices")
    return points[:, 1:], batch.long()


def image_levels_bv(levels: Any, batch_size: int, num_cameras: int, name: str) -> List[Tensor]:
    """Image feature levels as ``(B, C, H, W)`` (one camera) or ``(B, V, C, H, W)``.

    Frameworks run the image backbone on ``(B*V, C, H, W)`` (views folded into the batch, in the
    order of the per-sample camera list); such levels are unfolded to ``(B, V, C, H, W)``.
    """
    if isinstance(levels, Tensor) or not isinstance(levels, (list, tuple)) or not levels:
        raise MSSFError(f"{name}: expected a non-empty list/tuple of image levels, got {type(levels).__name__}")
    out = []
    for i, lvl in enumerate(levels):
        if not isinstance(lvl, Tensor):
            raise MSSFError(f"{name}[{i}]: expected a tensor, got {type(lvl).__name__}")
        if lvl.dim() == 5:
            if tuple(lvl.shape[:2]) != (batch_size, num_cameras):
                raise MSSFError(f"{name}[{i}]: expected (B={batch_size}, V={num_cameras}, C, H, W), got {tuple(lvl.shape)}")
        elif lvl.dim() == 4:
            if num_cameras > 1 or lvl.shape[0] != batch_size:
                if lvl.shape[0] != batch_size * num_cameras:
                    raise MSSFError(
                        f"{name}[{i}]: expected (B*V={batch_size * num_cameras}, C, H, W) or (B, V, C, H, W) "
                        f"(B={batch_size}, V={num_cameras}), got {tuple(lvl.shape)}"
                    )
                lvl = lvl.reshape(batch_size, num_cameras, *lvl.shape[1:])
        else:
            raise MSSFError(f"{name}[{i}]: expected a 4-d or 5-d tensor, got shape {tuple(lvl.shape)}")
        out.append(lvl)
    return out


def mmdet3d_seg_loss(seg_head: Any, out: Any, points: Sequence[Tensor], gt_bboxes_3d: Sequence[Any]) -> Tensor:
    """The semantic head's focal loss for an mmdet3d middle encoder's latest forward output ``out``.

    ``out`` carries ``seg_voxels`` (the voxels the head read) and ``seg_logits``; ``points`` are the
    per-sample points of that forward, ``gt_bboxes_3d`` per sample ``LiDARInstance3DBoxes`` (their
    ``.tensor``) or ``(G, 7+)`` tensors, mmdet3d's bottom-centre boxes. The centroids are recomputed from
    the points, as the head's foreground labels are defined on them.
    """
    from mssf_blocks.functional.geometry import voxel_centroids

    boxes = [getattr(b, "tensor", b)[:, :7] for b in gt_bboxes_3d]
    flat = torch.cat(list(points), 0)
    batch = torch.cat([torch.full((p.shape[0],), i, dtype=torch.long, device=flat.device) for i, p in enumerate(points)])
    v = out.seg_voxels
    centroids, _ = voxel_centroids(flat[:, :3], batch, v.coords, v.spatial_shape, v.batch_size, v.voxel_size,
                                   v.point_range_min, v.stride)
    return seg_head.loss_from_boxes(out.seg_logits, centroids.to(out.seg_logits.dtype), v.batch_index,
                                    [g.to(centroids) for g in boxes], origin="bottom")
