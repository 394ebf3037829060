"""The corner geometry of the ``"touched"`` plans, checked against hand-written loops, and the point
layouts they accept: MSDFF's ``(Q, L, 2, M, P)`` locations view and a plain ``(Q, M, L, P, 2)`` tensor
give the same bits.

``_top_left_cells`` computes the padded cell ids in the floating type while they are exact integers
there and in int64 beyond; ``_read_pixels`` finds the pixels some corner reads by marking only the
top-left cells and dilating. Both are compared with a per-point Python loop.
"""

import itertools

import pytest
import torch

from mssf_blocks import MSDFF
from mssf_blocks.functional.deform import touched as touched_mod
from mssf_blocks.functional.deform.touched import blocks, points
from mssf_blocks.functional.deform.touched.plans import _read_pixels, _top_left_cells
from mssf_blocks.functional.deform.touched.points import _LevelLoc


def _points(q, m, p, h, w, dtype, seed=0):
    """Floors of pixel coordinates well outside the map, on its borders and inside, as a _LevelLoc."""
    g = torch.Generator().manual_seed(seed)
    x0 = torch.randint(-6, w + 6, (q, m, p), generator=g).to(dtype)
    y0 = torch.randint(-6, h + 6, (q, m, p), generator=g).to(dtype)
    x0.view(-1)[:4] = torch.tensor([-2.0, -1.0, w - 1.0, float(w)], dtype=dtype)  # the clamp's edges
    y0.view(-1)[:4] = torch.tensor([-3.0, float(h), -1.0, h - 1.0], dtype=dtype)
    return _LevelLoc(x0, y0, x0, y0, torch.ones(q, m, p, dtype=dtype))


def _naive_cell(i, y0, x0, h, w):
    yc = min(max(int(y0), -2), h) + 2
    xc = min(max(int(x0), -2), w) + 2
    return (i * (h + 4) + yc) * (w + 4) + xc


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_top_left_cells_float_and_int64_paths_equal_a_loop(dtype):
    q, m, p, h, w = 7, 3, 2, 5, 9
    lv = _points(q, m, p, h, w, dtype)
    image_index = torch.tensor([0, 2, 1, 2, 0, 1, 2])
    expected = torch.tensor([[[_naive_cell(int(image_index[a]), lv.y0[a, b, c], lv.x0[a, b, c], h, w)
                               for c in range(p)] for b in range(m)] for a in range(q)])
    float_path = _top_left_cells(lv, image_index, 3, h, w)
    # as many images as make the cell ids inexact in float32 / float64: the int64 path
    many = 2**53 // ((h + 4) * (w + 4)) + 1 if dtype == torch.float64 else 2**24 // ((h + 4) * (w + 4)) + 1
    int_path = _top_left_cells(lv, image_index, many, h, w)
    assert float_path.dtype == int_path.dtype == torch.int64
    assert torch.equal(float_path, expected)
    assert torch.equal(int_path, expected)


def test_top_left_cells_float_path_exact_at_the_largest_cell_id():
    # the last image of a batch just below the float32 bound: every id still exact
    h, w = 60, 90
    per_image = (h + 4) * (w + 4)
    num_images = (2**24 - 1) // per_image
    x, y = torch.full((1, 1, 1), float(w)), torch.full((1, 1, 1), float(h))
    lv = _LevelLoc(x, y, x, y, torch.ones(1, 1, 1))
    cells = _top_left_cells(lv, torch.tensor([num_images - 1]), num_images, h, w)
    assert cells.item() == _naive_cell(num_images - 1, h, w, h, w) < 2**24


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_read_pixels_are_the_in_map_corners_of_every_point(seed):
    q, m, p, h, w, num_images = 11, 2, 3, 6, 8, 2
    lv = _points(q, m, p, h, w, torch.float32, seed)
    image_index = torch.randint(0, num_images, (q,), generator=torch.Generator().manual_seed(seed))
    expected = torch.zeros(num_images, h, w, dtype=torch.bool)
    for a, b, c in itertools.product(range(q), range(m), range(p)):
        for dy, dx in itertools.product((0, 1), (0, 1)):
            y, x = int(lv.y0[a, b, c]) + dy, int(lv.x0[a, b, c]) + dx
            if 0 <= y < h and 0 <= x < w:
                expected[image_index[a], y, x] = True
    got = _read_pixels(_top_left_cells(lv, image_index, num_images, h, w), num_images, h, w)
    assert torch.equal(got, expected)


def test_msdff_locations_are_a_level_major_view_with_the_reference_values():
    torch.manual_seed(0)
    e, c, m, lv_, p = 12, 16, 4, 3, 2
    mod = MSDFF(c, e, num_heads=m, num_levels=lv_, num_points=p).double()
    with torch.no_grad():
        mod.sampling_offsets.weight.normal_(0.0, 0.5)
        mod.attention_weights.weight.normal_(0.0, 0.5)
    q = 9
    query, uv = torch.randn(q, e, dtype=torch.float64), torch.rand(q, 2, dtype=torch.float64)
    sizes = [(20, 30), (10, 15), (5, 8)]
    loc, wt = mod.sampling_locations_and_weights(query, uv, sizes)
    off = (query @ mod.sampling_offsets.weight.T + mod.sampling_offsets.bias).view(q, m, lv_, p, 2)
    norm = torch.tensor([[w, h] for h, w in sizes], dtype=torch.float64).view(1, 1, lv_, 1, 2)
    torch.testing.assert_close(loc, uv.view(q, 1, 1, 1, 2) + off / norm, rtol=0, atol=1e-12)
    logits = (query @ mod.attention_weights.weight.T + mod.attention_weights.bias).view(q, m, lv_ * p)
    torch.testing.assert_close(wt, logits.softmax(-1).view(q, m, lv_, p), rtol=0, atol=1e-12)
    # one level's x (or y) of all heads and points is one contiguous run per query
    assert loc.permute(0, 2, 4, 1, 3).is_contiguous()


@pytest.mark.parametrize("layout", ["nchw", "channels_last"])
def test_touched_output_independent_of_the_locations_layout(layout, monkeypatch):
    torch.manual_seed(1)
    q, m, p, d, dch = 40, 4, 2, 3, 8
    sizes = [(12, 17), (6, 9)]
    values = [torch.randn(2, 1, dch, h, w) for h, w in sizes]
    if layout == "channels_last":
        values = [v.squeeze(1).contiguous(memory_format=torch.channels_last).unsqueeze(1) for v in values]
    image_index = torch.randint(0, 2, (q,))
    plain = torch.rand(q, m, len(sizes), p, 2) * 1.2 - 0.1
    as_view = plain.permute(0, 2, 4, 1, 3).contiguous().permute(0, 3, 1, 4, 2)  # MSDFF's memory order
    assert torch.equal(as_view, plain) and not as_view.is_contiguous()
    weights = torch.rand(q, m, len(sizes), p)
    proj_w, proj_b = torch.randn(m, d, dch), torch.randn(m, d)
    for plan in ["dense", "project", "sample", None] + (["direct"] if layout == "channels_last" else []):
        a = touched_mod.sample_project(values, image_index, plain, weights, proj_w, proj_b, plan)
        b = touched_mod.sample_project(values, image_index, as_view, weights, proj_w, proj_b, plan)
        assert torch.equal(a, b), plan
    # and blocks of 7 queries for the raw-row plans give the same values as one block
    monkeypatch.setattr(blocks, "_RAW_CHUNK_BYTES", m * dch * 4 * 7)
    c = touched_mod.sample_project(values, image_index, as_view, weights, proj_w, proj_b, "sample")
    torch.testing.assert_close(c, touched_mod.sample_project(values, image_index, plain, weights, proj_w,
                                                                        proj_b, "dense"), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("dtype,p,width", [(torch.float32, 4, torch.complex128), (torch.float32, 2, torch.int64),
                                           (torch.float32, 3, torch.float32), (torch.float64, 4, torch.complex128),
                                           (torch.float64, 1, torch.float64), (torch.int32, 2, torch.int64)])
def test_wide_views_whole_runs_and_moves_the_same_bits(dtype, p, width):
    t = (torch.randn(5, 3, 2, p) * 100).to(dtype)
    wide = points._wide(t)
    assert wide.dtype == width  # the widest of 16 / 8 / 4 bytes dividing p elements, else t itself
    if wide is not t:
        assert wide.data_ptr() == t.data_ptr()  # a view, no copy
    # a permuted copy through the view equals the plain permuted copy bit for bit (NaNs included)
    t.view(-1)[::7] = float("nan") if dtype.is_floating_point else -1
    moved = points._wide(t).permute(0, 2, 1, 3).contiguous().view(dtype).view(5, 2, 3, p)
    expected = t.permute(0, 2, 1, 3).contiguous()
    assert torch.equal(moved.view(torch.uint8) if dtype.is_floating_point else moved,
                       expected.view(torch.uint8) if dtype.is_floating_point else expected)


def test_wide_leaves_what_it_cannot_view_and_what_autograd_records():
    odd = torch.randn(4, 3)  # 12 bytes a row: no wider element divides them
    assert points._wide(odd) is odd
    strided = torch.randn(4, 8)[:, 1:5]  # a run of 16 bytes at an offset of 4 bytes
    assert points._wide(strided) is strided
    leaf = torch.randn(4, 4, requires_grad=True)
    assert points._wide(leaf) is leaf
    with torch.no_grad():
        assert points._wide(leaf).dtype == torch.complex128


@pytest.mark.parametrize("requires_grad", [False, True])
def test_sorted_points_weights_are_the_level_major_permutation(requires_grad):
    q, m, lv_, p = 6, 3, 2, 4
    g = torch.Generator().manual_seed(5)
    loc = torch.rand(q, m, lv_, p, 2, generator=g)
    wt = torch.rand(q, m, lv_, p, generator=g).requires_grad_(requires_grad)
    order = torch.tensor([3, 0, 5, 1, 4, 2])
    _, wts = points._sorted_points(loc, wt, [(4, 6), (2, 3)], order)
    expected = torch.stack([torch.stack([wt[order[a], :, b] for b in range(lv_)]) for a in range(q)])
    assert torch.equal(wts.detach(), expected.detach())
    assert wts.requires_grad == requires_grad  # (a dtype view would have cut the graph)
    if requires_grad:
        (grad,) = torch.autograd.grad((wts * expected.detach()).sum(), wt)
        assert torch.equal(grad, wt.detach())


@pytest.mark.parametrize("layout", ["msdff_view", "contiguous", "sliced", "expanded"])
def test_rows_gathers_in_memory_order_with_index_selects_values_and_gradients(layout):
    """``points._rows`` (the plans' query gather) equals a per-row Python loop, values and gradients; for
    MSDFF's ``(Q, M, L, P, 2)`` view of ``(Q, L, 2, M, P)`` memory it gathers whole rows of that memory
    (the result is the same view of gathered rows), not element by element."""
    q, m, lv, p = 9, 3, 2, 4
    g = torch.Generator().manual_seed(3)
    base = torch.randn(q, lv, 2, m, p, generator=g, dtype=torch.float64, requires_grad=True)
    make = {
        "msdff_view": lambda b: b.permute(0, 3, 1, 4, 2),
        "contiguous": lambda b: b.permute(0, 3, 1, 4, 2).contiguous(),
        "sliced": lambda b: b[:, :, :, 1:],  # (Q, L, 2, M - 1, P): not dense
        "expanded": lambda b: b[:, :1, :1, :1, :1].expand(q, m, lv, p, 2),  # stride 0
    }[layout]
    index = torch.tensor([4, 0, 8, 2, 7])
    out = points._rows(make(base), index)
    expected = torch.stack([make(base)[i] for i in index.tolist()])
    assert out.shape == expected.shape and torch.equal(out, expected)
    if layout == "msdff_view":
        assert out.permute(0, 2, 4, 1, 3).is_contiguous()
    grad = torch.randn(expected.shape, generator=g, dtype=torch.float64)
    (got,) = torch.autograd.grad(out, base, grad)
    (want,) = torch.autograd.grad(expected, base, grad)
    assert torch.equal(got, want)
