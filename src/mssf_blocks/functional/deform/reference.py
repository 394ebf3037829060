"""The float64 reference of multi-scale deformable sampling: Deformable DETR's per-level ``F.grid_sample``
formulation, which the tests hold every backend to."""

from __future__ import annotations

from typing import Sequence, Tuple, Union

import torch.nn.functional as F
from torch import Tensor

__all__ = ["ms_deform_sample_reference"]


def ms_deform_sample_reference(
    values: Sequence[Tensor],
    image_index: Tensor,
    locations: Tensor,
    weights: Tensor,
    return_mass: bool = False,
) -> Union[Tensor, Tuple[Tensor, Tensor]]:
    """Per-level ``F.grid_sample`` formulation of :func:`ms_deform_sample` (no input validation).

    The well-known pure-PyTorch Deformable DETR formulation (grid ``2 * loc - 1``,
    ``align_corners=False``, zero padding), looping over levels and images (never over queries).
    ``mass`` is computed independently by sampling a map of ones.
    """
    q, m, _, p, _ = locations.shape
    num_images, mv, d = values[0].shape[:3]
    out = locations.new_zeros(q, m, d)
    mass = locations.new_zeros(q, m)
    if q == 0:  # keep a graph (of zeros) so that an empty batch can still be backpropagated
        out = out + 0.0 * locations.sum() + 0.0 * weights.sum()
        mass = mass + 0.0 * weights.sum()
    grid = 2.0 * locations - 1.0
    per_image = [(image_index == i).nonzero(as_tuple=True)[0] for i in range(num_images)]
    for lvl, val in enumerate(values):
        h, w = val.shape[-2:]
        for i, sel in enumerate(per_image):
            qi = sel.numel()
            if qi == 0:
                continue
            g = grid[sel, :, lvl]  # (qi, M, P, 2)
            wt = weights[sel, :, lvl]  # (qi, M, P)
            if mv == 1:
                g = g.reshape(1, qi * m, p, 2)
            else:
                g = g.transpose(0, 1)  # (M, qi, P, 2): head m samples value head m
            s = F.grid_sample(val[i], g, mode="bilinear", padding_mode="zeros", align_corners=False)
            s = s.reshape(mv, d, qi, m // mv, p) if mv == 1 else s.reshape(m, d, qi, 1, p)
            # s[.., d, q, m or 1, p] -> (qi, M, D)
            s = s.permute(2, 0, 3, 1, 4).reshape(qi, m, d, p)
            out = out.index_add(0, sel, (s * wt[:, :, None, :]).sum(-1))
            if return_mass:
                ones = val.new_ones(1, 1, h, w)
                gm = g.reshape(1, -1, p, 2)
                one = F.grid_sample(ones, gm, mode="bilinear", padding_mode="zeros", align_corners=False)
                one = one.reshape(mv, -1, p)  # (Mv, qi*M/Mv or qi, P)
                one = one.reshape(qi, m, p) if mv == 1 else one.transpose(0, 1)
                mass = mass.index_add(0, sel, (one * wt).sum(-1))
    return (out, mass) if return_mass else out
