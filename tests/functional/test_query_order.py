"""The order in which the ``"touched"`` plans take the queries: a Hilbert curve over the image.

``_hilbert_index`` is compared with the curve built the other way round, by its recursive definition
(four copies of the curve one order lower, the first transposed and the last turned the other way);
``_spatial_order`` with the properties the bags rely on: a permutation, images one after another,
neighbouring queries neighbours in the image (also on a level that is not square), and results that
do not depend on it.
"""

import pytest
import torch

from mssf_blocks.functional.deform import touched as touched_mod
from mssf_blocks.functional.deform.touched import order as order_mod
from mssf_blocks.functional.deform.touched.order import _hilbert_index, _spatial_order
from mssf_blocks.functional.plan_costs import _SORT_CELL


def _curve(bits):
    """The cells of the ``2**bits``-sided square in Hilbert order, from the recursive definition: the
    order-``k`` curve is the order-``k - 1`` curve transposed (lower left), shifted up (upper left),
    shifted up and right (upper right), and reflected in the anti-diagonal, shifted right (lower right)."""
    cells = [(0, 0)]
    for k in range(bits):
        s = 1 << k
        cells = ([(y, x) for x, y in cells] + [(x, y + s) for x, y in cells]
                 + [(x + s, y + s) for x, y in cells] + [(2 * s - 1 - y, s - 1 - x) for x, y in cells])
    return cells


def test_curve_reference_is_the_textbook_first_orders():
    assert _curve(1) == [(0, 0), (0, 1), (1, 1), (1, 0)]
    assert _curve(2)[:8] == [(0, 0), (1, 0), (1, 1), (0, 1), (0, 2), (0, 3), (1, 3), (1, 2)]


@pytest.mark.parametrize("bits", [1, 2, 3, 4, 5, 6, 8, 9])
def test_hilbert_index_equals_the_recursive_curve(bits):
    cells = _curve(bits)
    x = torch.tensor([c[0] for c in cells])
    y = torch.tensor([c[1] for c in cells])
    assert torch.equal(_hilbert_index(x, y, bits), torch.arange(len(cells)))
    # (and the reference is a curve: a bijection whose consecutive cells are 4-neighbours)
    assert len(set(cells)) == 4**bits
    assert all(abs(a[0] - b[0]) + abs(a[1] - b[1]) == 1 for a, b in zip(cells, cells[1:]))


def _locations(u, v, m=2, levels=1, p=1):
    """``(Q, M, L, P, 2)`` locations whose first point is ``(u, v)`` (the others far away)."""
    loc = torch.rand(u.numel(), m, levels, p, 2)
    loc[:, 0, 0, 0, 0], loc[:, 0, 0, 0, 1] = u, v
    return loc


@pytest.mark.parametrize("size", [(16, 16), (8, 32), (40, 10)])
def test_spatial_order_walks_the_image_in_neighbouring_cells(size):
    h, w = size
    cell = _SORT_CELL
    # one query at the centre of every cell of the curve's grid, in a shuffled order, on two images
    rows, cols = int(h / cell), int(w / cell)
    yy, xx = torch.meshgrid(torch.arange(rows), torch.arange(cols), indexing="ij")
    u = ((xx.reshape(-1) + 0.5) * cell / w).repeat(2)
    v = ((yy.reshape(-1) + 0.5) * cell / h).repeat(2)
    image = torch.arange(2).repeat_interleave(rows * cols)
    shuffle = torch.randperm(u.numel(), generator=torch.Generator().manual_seed(0))
    u, v, image = u[shuffle], v[shuffle], image[shuffle]
    order = _spatial_order(image, _locations(u, v), [size])
    assert torch.equal(order.sort().values, torch.arange(u.numel()))  # a permutation
    assert torch.equal(image[order], image.sort().values)  # by image first
    # the grid is the curve's (its cells are square in pixels, the longer side spans the curve):
    # consecutive queries of an image are in neighbouring cells unless the curve leaves the image
    # and comes back (a short side shorter than the curve's square); the mean step stays about a cell
    col, row = (u[order] * w / cell).floor(), (v[order] * h / cell).floor()
    step = (col[1:] - col[:-1]).abs() + (row[1:] - row[:-1]).abs()
    same = image[order][1:] == image[order][:-1]
    if rows == cols:
        assert torch.equal(step[same], torch.ones(int(same.sum())))
    else:
        assert (step[same] == 1).float().mean() > 0.8
        assert step[same].float().mean() < 1.5


def test_spatial_order_keeps_a_block_of_queries_on_fewer_pixels_than_bands_of_rows():
    # 4,096 random queries on a 256 x 512 level, in blocks of 64, each reading the pixels within 8 of
    # it (its points' spread): a block reads about half as many distinct pixels along the curve as in
    # the bands of rows it replaced (one band a block here: a 512 x 4 strip against a square patch)
    h, w, n, block, reach = 256, 512, 4096, 64, 8
    g = torch.Generator().manual_seed(3)
    u, v = torch.rand(n, generator=g), torch.rand(n, generator=g)
    order = _spatial_order(torch.zeros(n, dtype=torch.long), _locations(u, v), [(h, w), (h // 2, w // 2)])
    bands = torch.argsort((v * 63).round().long() * 4096 + (u * 4095).round().long())
    offsets = torch.arange(-reach, reach + 1)

    def pixels_per_block(perm):
        x = (u[perm] * w).long().view(-1, block, 1, 1) + offsets.view(1, 1, -1, 1)
        y = (v[perm] * h).long().view(-1, block, 1, 1) + offsets.view(1, 1, 1, -1)
        ids = (y.clamp(0, h - 1) * w + x.clamp(0, w - 1)).view(n // block, -1)
        return sum(row.unique().numel() for row in ids) / (n // block)

    ratio = pixels_per_block(order) / pixels_per_block(bands)
    assert ratio < 0.6, ratio


def test_touched_results_do_not_depend_on_the_order(monkeypatch):
    torch.manual_seed(2)
    q, m, p, d, dch = 60, 4, 2, 3, 8
    sizes = [(12, 17), (6, 9)]
    values = [torch.randn(2, 1, dch, h, w).squeeze(1).contiguous(memory_format=torch.channels_last).unsqueeze(1)
              for h, w in sizes]
    image_index = torch.randint(0, 2, (q,))
    loc = torch.rand(q, m, len(sizes), p, 2) * 1.2 - 0.1
    weights = torch.rand(q, m, len(sizes), p)
    proj_w, proj_b = torch.randn(m, d, dch), torch.randn(m, d)
    for plan in ("dense", "project", "sample", "direct", None):
        ours = touched_mod.sample_project(values, image_index, loc, weights, proj_w, proj_b, plan)
        with monkeypatch.context() as mp:  # the callers' order, and its reverse
            for perm in (torch.arange(q), torch.arange(q).flip(0)):
                mp.setattr(order_mod, "_spatial_order", lambda *a, perm=perm: perm)
                other = touched_mod.sample_project(values, image_index, loc, weights, proj_w, proj_b,
                                                              plan)
                assert torch.equal(ours, other), plan
