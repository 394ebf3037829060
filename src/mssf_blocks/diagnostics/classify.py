"""Feature-blurring classes of projected points: 2D foreground, 3D foreground, 3D blurred.

The definitions (paper Sec. I, Fig. 1) and the image-coordinate conventions are in
:mod:`mssf_blocks.diagnostics`; import these names from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence, Tuple

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import (
    INDEX_DTYPES,
    check_dtype,
    check_finite,
    check_floating,
    check_index_range,
    check_shape,
)
from mssf_blocks.checks.arguments import check_image_size
from mssf_blocks.errors import MSSFError
from mssf_blocks.checks.boxes import check_boxes
from mssf_blocks.functional.heads import points_in_boxes
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection

__all__ = ["BlurClassification", "classify_feature_blurring", "classify_projection", "instance_foreground_counts"]



@dataclass(frozen=True)
class BlurClassification:
    """Per-point classes of :func:`classify_feature_blurring` (all ``(N,)`` bool).

    Attributes:
        fore2d: projection inside a 2D box / mask (in at least one camera where it is valid).
        fore3d: ``fore2d`` and inside a 3D ground-truth box.
        blurred: ``fore2d`` and not inside any 3D ground-truth box.
        in_box3d: inside a 3D ground-truth box, whatever the projection (the head's foreground).
    """

    fore2d: Tensor
    fore3d: Tensor
    blurred: Tensor
    in_box3d: Tensor

    @property
    def n_fore2d(self) -> int:
        return int(self.fore2d.sum())

    @property
    def n_fore3d(self) -> int:
        return int(self.fore3d.sum())

    @property
    def n_blurred(self) -> int:
        return int(self.blurred.sum())

    def counts(self) -> dict:
        """``{"points", "fore2d", "fore3d", "blurred", "in_box3d"}`` as ints."""
        return {
            "points": int(self.fore2d.shape[0]),
            "fore2d": self.n_fore2d,
            "fore3d": self.n_fore3d,
            "blurred": self.n_blurred,
            "in_box3d": int(self.in_box3d.sum()),
        }

    @staticmethod
    def from_masks(fore2d: Tensor, in_box3d: Tensor) -> "BlurClassification":
        """Build the classes from the two primary masks (``(N,)`` bool each)."""
        check_shape(fore2d, "fore2d", ("N",))
        check_shape(in_box3d, "in_box3d", (fore2d.shape[0],))
        check_dtype(fore2d, "fore2d", (torch.bool,))
        check_dtype(in_box3d, "in_box3d", (torch.bool,))
        return BlurClassification(fore2d, fore2d & in_box3d, fore2d & ~in_box3d, in_box3d)


# -- classification ---------------------------------------------------------------------------------
def _check_per_centroid(centroids: Tensor, batch_index: Tensor, uv: Tensor, valid, gt_boxes):
    """Shared checks: one batch index and one projection row per centroid, batch indices < len(gt_boxes).

    Returns the normalised ``(uv, valid)``.
    """
    n = centroids.shape[0]
    check_shape(batch_index, "batch_index", (n,))
    check_dtype(batch_index, "batch_index", INDEX_DTYPES)
    uv, valid = _normalize_uv(uv, valid)
    if uv.shape[0] != n:
        raise MSSFError(f"uv: expected {n} rows (one per centroid), got shape {tuple(uv.shape)}")
    if isinstance(gt_boxes, Tensor) or not isinstance(gt_boxes, Sequence):
        raise MSSFError(f"gt_boxes: expected a list with one (G_b, 7) tensor per sample, got {type(gt_boxes).__name__}")
    check_index_range(batch_index, "batch_index", len(gt_boxes), "len(gt_boxes)")
    return uv, valid


def _normalize_uv(uv: Tensor, valid: Optional[Tensor]) -> Tuple[Tensor, Tensor]:
    check_floating(check_finite(_tensor(uv, "uv"), "uv"), "uv")
    if uv.dim() == 2:
        uv = uv[:, None]
        if valid is not None and isinstance(valid, Tensor) and valid.dim() == 1:
            valid = valid[:, None]
    check_shape(uv, "uv", ("N", "V", 2))
    n, v = uv.shape[:2]
    if valid is None:
        valid = torch.ones(n, v, dtype=torch.bool, device=uv.device)
    check_shape(valid, "valid", (n, v))
    check_dtype(valid, "valid", (torch.bool,))
    return uv, valid


def _tensor(x, name: str) -> Tensor:
    if not isinstance(x, Tensor):
        raise MSSFError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    return x




def _check_boxes_2d(boxes_2d, batch_size: int, num_cameras: int) -> list:
    if isinstance(boxes_2d, Tensor) or not isinstance(boxes_2d, Sequence):
        raise MSSFError(
            f"boxes_2d: expected a list with one (K_b, 4) or (K_b, 5) tensor per sample, "
            f"got {type(boxes_2d).__name__}"
        )
    if len(boxes_2d) != batch_size:
        raise MSSFError(f"boxes_2d: expected {batch_size} entries (len(gt_boxes)), got {len(boxes_2d)}")
    out = []
    for i, boxes in enumerate(boxes_2d):
        name = f"boxes_2d[{i}]"
        check_shape(boxes, name, ("K", None))
        check_floating(boxes, name)
        check_finite(boxes, name)
        if boxes.shape[1] == 4:
            if num_cameras != 1:
                raise MSSFError(
                    f"{name}: with V={num_cameras} cameras expected (K, 5) rows (camera, x1, y1, x2, y2), "
                    f"got shape {tuple(boxes.shape)}"
                )
            boxes = torch.cat([boxes.new_zeros(boxes.shape[0], 1), boxes], dim=1)
        elif boxes.shape[1] != 5:
            raise MSSFError(
                f"{name}: expected shape (K, 4) (x1, y1, x2, y2) or (K, 5) (camera, x1, y1, x2, y2), "
                f"got {tuple(boxes.shape)}"
            )
        if boxes.shape[0]:
            cam = boxes[:, 0]
            if bool((cam != cam.round()).any()) or int(cam.min()) < 0 or int(cam.max()) >= num_cameras:
                raise MSSFError(f"{name}: expected integer camera indices in [0, {num_cameras}) in column 0")
            if bool((boxes[:, 3] < boxes[:, 1]).any() | (boxes[:, 4] < boxes[:, 2]).any()):
                raise MSSFError(f"{name}: expected x1 <= x2 and y1 <= y2")
        out.append(boxes)
    return out


def _in_boxes_2d(pixel: Tensor, valid: Tensor, batch_index: Tensor, boxes_2d: list) -> Tensor:
    """``(N,)``: the point projects (validly) inside some 2D box of its own sample."""
    n = pixel.shape[0]
    hit = torch.zeros(n, dtype=torch.bool, device=pixel.device)
    for b, boxes in enumerate(boxes_2d):
        rows = (batch_index == b).nonzero().flatten()
        if rows.numel() == 0 or boxes.shape[0] == 0:
            continue
        hit[rows] = _box_hits(pixel[rows], valid[rows], boxes.to(pixel.device)).any(dim=1)
    return hit


def _box_hits(pixel: Tensor, valid: Tensor, boxes: Tensor) -> Tensor:
    """``(n, K)``: point projects (validly, in the box's camera) inside 2D box ``k``."""
    boxes = boxes.to(pixel.dtype)
    cam = boxes[:, 0].long()
    p = pixel[:, cam]  # (n, K, 2): each point's pixel in the camera of box k
    ok = valid[:, cam]
    return (
        ok
        & (p[..., 0] >= boxes[:, 1]) & (p[..., 0] <= boxes[:, 3])
        & (p[..., 1] >= boxes[:, 2]) & (p[..., 1] <= boxes[:, 4])
    )


def _in_masks(uv: Tensor, valid: Tensor, batch_index: Tensor, masks: Tensor, batch_size: int) -> Tensor:
    if masks.dim() == 3:
        masks = masks[:, None]
    check_shape(masks, "masks", (batch_size, uv.shape[1], "H_m", "W_m"))
    check_dtype(masks, "masks", (torch.bool,))
    hm, wm = masks.shape[2:]
    # Normalised uv -> pixel index of a mask at any resolution: floor(uv * size).
    col = torch.floor(uv[..., 0] * wm).long()
    row = torch.floor(uv[..., 1] * hm).long()
    inside = valid & (col >= 0) & (col < wm) & (row >= 0) & (row < hm)
    cam = torch.arange(uv.shape[1], device=uv.device).expand(uv.shape[0], -1)
    b = batch_index[:, None].expand(-1, uv.shape[1])
    hit = masks[b, cam, row.clamp(0, hm - 1), col.clamp(0, wm - 1)] & inside
    return hit.any(dim=1)


def classify_feature_blurring(
    centroids: Tensor,
    batch_index: Tensor,
    uv: Tensor,
    gt_boxes: Sequence[Tensor],
    boxes_2d: Optional[Sequence[Tensor]] = None,
    masks: Optional[Tensor] = None,
    image_size: Optional[Sequence[int]] = None,
    valid: Optional[Tensor] = None,
    origin: str = "center",
) -> BlurClassification:
    """Classify projected points into 2D foreground, 3D foreground and 3D blurred (paper Fig. 1(a)).

    Give exactly one of ``boxes_2d`` (Fig. 7's 2D ground-truth boxes) or ``masks`` (Fig. 1's instance
    masks). With several cameras a point is 2D foreground when it is in a box/mask of any camera where
    its projection is valid.

    Args:
        centroids: ``(N, 3+)`` sensor-frame ``x, y, z`` of the points / voxel centroids.
        batch_index: ``(N,)`` integer sample of every point.
        uv: ``(N, V, 2)`` (or ``(N, 2)`` for one camera) normalised image coordinates.
        gt_boxes: length-``B`` list of ``(G_b, 7+)`` 3D boxes ``(x, y, z, dx, dy, dz, yaw)``.
        boxes_2d: length-``B`` list of ``(K_b, 4)`` ``(x1, y1, x2, y2)`` pixel boxes (one camera) or
            ``(K_b, 5)`` ``(camera, x1, y1, x2, y2)``.
        masks: ``(B, V, H_m, W_m)`` or ``(B, H_m, W_m)`` bool union of the instance masks of each
            image, at any resolution (looked up at pixel ``floor(uv * (W_m, H_m))``).
        image_size: ``(H, W)`` the uv are relative to; required with ``boxes_2d``.
        valid: optional ``(N, V)`` (or ``(N,)``) bool, e.g. ``CentroidProjection.valid``; invalid
            projections are never 2D foreground.
        origin: 3D box ``z`` convention, ``"center"`` or ``"bottom"`` (see
            :func:`mssf_blocks.functional.heads.points_in_boxes`).

    Returns:
        :class:`BlurClassification`.
    """
    check_shape(centroids, "centroids", ("N", None))
    check_floating(centroids, "centroids")
    if centroids.shape[1] < 3:
        raise MSSFError(f"centroids: expected shape (N, >=3), got {tuple(centroids.shape)}")
    uv, valid = _check_per_centroid(centroids, batch_index, uv, valid, gt_boxes)
    batch_size = len(gt_boxes)
    if (boxes_2d is None) == (masks is None):
        raise MSSFError("boxes_2d, masks: expected exactly one of them (2D boxes or instance masks), "
                        f"got {'both' if masks is not None else 'neither'}")
    b = batch_index.long()
    uv = uv.detach()
    if boxes_2d is not None:
        if image_size is None:
            raise MSSFError("image_size: expected (H, W) to turn uv into pixel coordinates for boxes_2d, got None")
        h, w = check_image_size(image_size)
        boxes = _check_boxes_2d(boxes_2d, batch_size, uv.shape[1])
        size = torch.tensor([w, h], dtype=uv.dtype, device=uv.device)
        fore2d = _in_boxes_2d(uv * size - 0.5, valid, b, boxes)
    else:
        fore2d = _in_masks(uv, valid, b, _tensor(masks, "masks"), batch_size)
    in_box3d = torch.zeros(centroids.shape[0], dtype=torch.bool, device=centroids.device)
    xyz = centroids[:, :3].detach()
    for i, boxes in enumerate(gt_boxes):
        rows = (b == i).nonzero().flatten()
        # Validate every sample's boxes, also where it has no points.
        hits = points_in_boxes(xyz[rows], check_boxes(boxes, f"gt_boxes[{i}]").to(xyz.device), origin=origin)
        if rows.numel():
            in_box3d[rows] = hits.any(dim=1)
    return BlurClassification.from_masks(fore2d, in_box3d)


def classify_projection(
    projection: CentroidProjection,
    gt_boxes: Sequence[Tensor],
    boxes_2d: Optional[Sequence[Tensor]] = None,
    masks: Optional[Tensor] = None,
    image_size: Optional[Sequence[int]] = None,
    origin: str = "center",
) -> BlurClassification:
    """:func:`classify_feature_blurring` of the voxel centroids of a :class:`CentroidProjection`."""
    if not isinstance(projection, CentroidProjection):
        raise MSSFError(f"projection: expected a CentroidProjection, got {type(projection).__name__}")
    return classify_feature_blurring(
        projection.centroid, projection.batch_index, projection.uv, gt_boxes, boxes_2d, masks,
        image_size, projection.valid, origin,
    )


def instance_foreground_counts(
    centroids: Tensor,
    batch_index: Tensor,
    uv: Tensor,
    image_size: Sequence[int],
    gt_boxes: Sequence[Tensor],
    boxes_2d: Sequence[Tensor],
    valid: Optional[Tensor] = None,
    origin: str = "center",
) -> Tuple[Tensor, Tensor]:
    """Per-instance counts behind paper Fig. 1(d) (``ratio = n_fore3d / n_fore2d`` per instance).

    Row ``k`` of ``boxes_2d[b]`` and row ``k`` of ``gt_boxes[b]`` must be the same object (KITTI-style
    labels give both). For instance ``k``: ``n_fore2d`` counts the points projecting into its 2D box,
    ``n_fore3d`` those of them that are also inside its 3D box.

    Returns:
        ``n_fore2d (K,)`` and ``n_fore3d (K,)`` int64 over all instances, samples in order. Average
        ``n_fore3d / n_fore2d`` over the instances with ``n_fore2d > 0`` (per class) for Fig. 1(d).
    """
    check_shape(centroids, "centroids", ("N", None))
    check_floating(centroids, "centroids")
    uv, valid = _check_per_centroid(centroids, batch_index, uv, valid, gt_boxes)
    h, w = check_image_size(image_size)
    boxes2 = _check_boxes_2d(boxes_2d, len(gt_boxes), uv.shape[1])
    pixel = uv.detach() * torch.tensor([w, h], dtype=uv.dtype, device=uv.device) - 0.5
    b = batch_index.long()
    n2, n3 = [], []
    for i, (box3, box2) in enumerate(zip(gt_boxes, boxes2)):
        if check_boxes(box3, f"gt_boxes[{i}]").shape[0] != box2.shape[0]:
            raise MSSFError(
                f"boxes_2d[{i}]: expected one row per 3D box ({box3.shape[0]} in gt_boxes[{i}]), "
                f"got {box2.shape[0]}"
            )
        rows = (b == i).nonzero().flatten()
        hit2 = _box_hits(pixel[rows], valid[rows], box2.to(pixel.device))  # (n_b, K)
        hit3 = points_in_boxes(centroids[rows, :3].detach(), box3.to(centroids.device), origin=origin)
        n2.append(hit2.sum(dim=0))
        n3.append((hit2 & hit3).sum(dim=0))
    if not n2:
        empty = torch.zeros(0, dtype=torch.long, device=centroids.device)
        return empty, empty
    return torch.cat(n2).long(), torch.cat(n3).long()

