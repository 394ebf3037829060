"""Independent references shared by the sampling tests (``test_bilinear_sample.py``, ``test_sampling.py``,
``test_deform_project.py``): bilinear interpolation and multi-scale deformable sampling by naive loops, random
inputs, and locations on pixel centres, pixel borders, image edges and outside.
"""

from __future__ import annotations

import math

import torch

F64 = torch.float64


def naive_bilinear(img: torch.Tensor, u: float, v: float) -> torch.Tensor:
    """Bilinear interpolation by hand: ``img (C, H, W)``, align_corners=False, zero padding."""
    c, h, w = img.shape
    x, y = u * w - 0.5, v * h - 0.5
    x0, y0 = math.floor(x), math.floor(y)
    out = torch.zeros(c, dtype=img.dtype)
    for yy in (y0, y0 + 1):
        for xx in (x0, x0 + 1):
            if 0 <= xx < w and 0 <= yy < h:
                wt = (1 - abs(x - xx)) * (1 - abs(y - yy))
                out += wt * img[:, yy, xx]
    return out


def naive_ms_deform(values, image_index, locations, weights):
    q, m, num_levels, p, _ = locations.shape
    d = values[0].shape[2]
    out = torch.zeros(q, m, d, dtype=locations.dtype)
    mass = torch.zeros(q, m, dtype=locations.dtype)
    for qi in range(q):
        for mi in range(m):
            for li in range(num_levels):
                val = values[li][int(image_index[qi])]
                img = val[mi if val.shape[0] > 1 else 0]
                ones = torch.ones(1, *img.shape[1:], dtype=img.dtype)
                for pi in range(p):
                    u, v = (float(t) for t in locations[qi, mi, li, pi])
                    wt = float(weights[qi, mi, li, pi])
                    out[qi, mi] += wt * naive_bilinear(img, u, v)
                    mass[qi, mi] += wt * naive_bilinear(ones, u, v)[0]
    return out, mass


def random_inputs(num_images=3, mv=1, m=2, d=3, sizes=((5, 7), (3, 4)), q=6, p=3, dtype=F64, seed=0, spread=0.3):
    g = torch.Generator().manual_seed(seed)
    values = [torch.randn(num_images, mv, d, h, w, generator=g, dtype=dtype) for h, w in sizes]
    locations = (torch.rand(q, m, len(sizes), p, 2, generator=g, dtype=dtype) * (1 + 2 * spread) - spread)
    weights = torch.rand(q, m, len(sizes), p, generator=g, dtype=dtype)
    image_index = torch.randint(0, num_images, (q,), generator=g)
    return values, image_index, locations, weights


def border_locations(sizes, q, m, p, dtype, seed=3):
    """Locations on pixel centres (integer pixel coords), pixel borders, image edges and outside."""
    g = torch.Generator().manual_seed(seed)
    locs = torch.empty(q, m, len(sizes), p, 2, dtype=dtype)
    for li, (h, w) in enumerate(sizes):
        for axis, n in ((0, w), (1, h)):
            # pixel coordinate x = u * n - 0.5 in {-1.5, -1, -0.5, 0, 0.5, ..., n - 0.5, n, n + 0.5}
            px = torch.arange(-3, 2 * n + 2, dtype=dtype) / 2
            pick = px[torch.randint(0, len(px), (q, m, p), generator=g)]
            locs[:, :, li, :, axis] = (pick + 0.5) / n
    return locs
