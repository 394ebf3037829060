"""The CPU backend of the sampling op: the ``"touched"`` plans (MSDFF's default on the CPU).

Read in this order, the order the data takes (each file entered once):

1. ``order.py``: the queries sorted by image, then along a Hilbert curve over the image;
2. ``points.py``: every level's points in one contiguous block of pixel coordinates;
3. ``plans.py``: per level the pixels the points' bilinear corners read, and the cheapest exact plan by
   the cost model of ``functional/plan_costs.py`` (project every pixel, project the touched pixels, or
   sample the touched pixels' raw channels and project per head), reading the level's raw rows;
4. ``blocks.py``: the four corners of every point, the levels bagged together in blocks of queries and
   summed;

then :func:`sample_project` puts the sum back in the callers' query order. The inputs are checked
once, at the op's entry (``functional/deform/op.py``); nothing here checks them again.
:func:`sample_points` serves ``bilinear_sample`` (one point per query, no projection) with the same
machinery.
"""

from __future__ import annotations

from typing import List, Optional

import torch
from torch import Tensor

from mssf_blocks.functional.deform.touched.blocks import _ProjectedLevel, _RawLevel, _sum_levels
from mssf_blocks.functional.deform.touched.order import _query_order
from mssf_blocks.functional.deform.touched.plans import _is_row_table, _touched_level
from mssf_blocks.functional.deform.touched.points import _level_points, _live_queries, _rows

__all__ = ["sample_project", "sample_points"]


def sample_project(
    levels: List[Tensor],
    image_index: Tensor,
    locations: Tensor,
    weights: Tensor,
    proj_weight: Tensor,
    proj_bias: Optional[Tensor],
    plan: Optional[str] = None,
    skip_unread: bool = False,
) -> Tensor:
    """``(Q, M, d)``: the op's formula for raw levels ``(I, 1, D, H_l, W_l)``, projection ``(M, d, D)``
    and ``(M, d)`` (or ``None``), per level by ``plan`` (``None``: the cheapest by the cost model).
    ``skip_unread``: first leave out the queries that read no pixel (zero rows; exact, see ``points.py``):
    the op's choice for static layouts, whose invalid (voxel, camera) pairs read nothing."""
    q, m, _, p, _ = locations.shape
    e = proj_weight.shape[0] * proj_weight.shape[1]
    d = proj_weight.shape[1]
    w_all = proj_weight.reshape(e, -1)
    b_all = None if proj_bias is None else proj_bias.reshape(e)
    sizes = [tuple(v.shape[-2:]) for v in levels]
    # Queries in image order: neighbouring queries then read neighbouring rows, which are still in
    # cache (the backward's per-corner dot products read the rows of 100-MiB levels in that order);
    # with skip_unread, the order leaves out the queries that read no pixel (points.py).
    live = _live_queries(locations, sizes) if skip_unread else None
    order, restore = _query_order(image_index, locations, sizes, live)
    if order.numel() == 0:  # keep a graph (of zeros) so that it can still be backpropagated
        out = locations.new_zeros(q, m, d) + 0.0 * (locations.sum() + weights.sum() + w_all.sum())
        return out if b_all is None else out + 0.0 * b_all.sum()
    needs_grad = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for t in [locations, weights, w_all, b_all, *levels]
    )
    image_index = image_index[order]
    if needs_grad:  # (the grid_sample plans read the points in the callers' layout; unbind: see _level_points)
        loc_levels, wt_levels = _rows(locations, order).unbind(2), _rows(weights, order).unbind(2)
    out = None
    raws: List[_RawLevel] = []
    projected: List[_ProjectedLevel] = []
    for lvl, (val, lv) in enumerate(zip(levels, _level_points(locations, weights, sizes, order))):
        if needs_grad:
            lv = lv._replace(loc=loc_levels[lvl], wt=wt_levels[lvl])
        part = _touched_level(val, image_index, lv, w_all, b_all, m, plan, needs_grad, defer_projection=True,
                              projection_paid=bool(raws))
        if isinstance(part, _RawLevel):  # bagged with the other levels in blocks of queries below
            raws.append(part)
        elif isinstance(part, _ProjectedLevel):
            projected.append(part)
        else:
            out = part if out is None else out.add_(part)  # (no backward here needs these outputs)
    if raws or projected:  # the sum of every level
        out = _sum_levels(raws, projected, w_all, b_all, m, needs_grad, base=out)
    if order.numel() < q:  # (the left-out queries' zero row)
        out = torch.cat([out, out.new_zeros(1, m, d)])
    return out.index_select(0, restore)  # back to the callers' order


def sample_points(image: Tensor, batch_index: Tensor, uv: Tensor) -> Tensor:
    """``(N, C)`` bilinear samples of ``image (B, 1, C, H, W)`` at the normalised points ``uv (N, 2)``
    of images ``batch_index (N,)``: the distinct in-map corner pixels gathered once (``"sample"``), or
    read in place from a channels-last map (``"direct"``), one ``embedding_bag``."""
    n = uv.shape[0]
    h, w = image.shape[-2:]
    ones = uv.new_ones(n, 1, 1, 1)
    lv = _level_points(uv.view(n, 1, 1, 1, 2), ones, [(h, w)])[0]
    plan = "direct" if _is_row_table(image) else "sample"
    return _touched_level(image, batch_index, lv, None, None, 1, plan)
