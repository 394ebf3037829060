"""Stage of ``benchmarks/gpu_check.py``: the sampling core on View-of-Delft shapes, three implementations.

* ``triton``: the sampling op's Triton kernels (``functional/deform/triton/kernels.py``; forward, and backward
  with the value gradient);
* ``grid``: the grid path (``functional/deform/grid.py``, one ``F.grid_sample`` per level, autograd);
* ``mmcv``: mmcv's ``MultiScaleDeformableAttnFunction`` (its CUDA op), where mmcv's compiled ops import;
  else, given an mmcv source archive (``mmcv_src``), its CUDA op built alone from it (``_mmcv_build.py``).

All read the same values: one ``(1, S, M, d)`` buffer of the ``L`` levels of a 1936 x 1216 image (FPN
strides 4-32 or 4-64), the grid path through ``(1, M, d, H_l, W_l)`` views of it. N = 2,500 / 8,000 /
20,000 queries, 8 heads, 4 points, d = 32 and 256, float32 and bfloat16 values (the locations and
weights float32 for the kernels and the grid path, which reads bfloat16 values as float32 like MSDFF;
mmcv takes one dtype for all three). Forward and forward +
backward times (CUDA-event medians), peak memory of forward + backward, and the largest difference
of the Triton and mmcv outputs from the grid path's. Targets (docs/performance.md): Triton forward +
backward >= 3x the grid path and no slower than mmcv's op at N = 8,000; peak memory <= 1/3 of the
grid path's. ``smoke`` (CPU): toy sizes, the grid path only (the kernels need a GPU, or the interpreter: ``TRITON_INTERPRET=1``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Dict, List, Optional

from _gpu_stages import _peak, _timer  # benchmarks/ (the script's folder) is on sys.path

__all__ = ["sampling_benchmark"]


def _mmcv_function(mmcv_src: Optional[Path], build_dir: Path):
    """``(mmcv's autograd function, None)`` or ``(None, why not)``: mmcv's own where its compiled ops
    import, else the op built from ``mmcv_src`` when given."""
    try:
        from mmcv.ops.multi_scale_deform_attn import MultiScaleDeformableAttnFunction, ext_module  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - not installed, or a build without compiled ops
        if mmcv_src is None:
            return None, (f"n/a ({type(exc).__name__}: {str(exc)[:80]}; --mmcv-src ARCHIVE builds its op from "
                          "mmcv's source)")
        import _mmcv_build

        print(f"  mmcv's compiled ops do not import: building its CUDA op from {mmcv_src}", flush=True)
        return _mmcv_build.function(mmcv_src, build_dir)
    return MultiScaleDeformableAttnFunction, None


def sampling_benchmark(device, smoke: bool, repeats: int, budget_s: float = 90.0, mmcv_src: Optional[Path] = None,
                       build_dir: Optional[Path] = None,
                       on_row: Optional[Callable[[Dict[str, object]], None]] = None,
                       mmcv_unavailable: Optional[str] = None) -> List[Dict[str, object]]:
    """One row per (levels, d, dtype, N); rows past ``budget_s`` seconds are listed as skipped. ``mmcv_src``:
    an mmcv source archive to build mmcv's op from where mmcv's compiled ops do not import (into
    ``build_dir``; the build's time is not counted in ``budget_s``). ``on_row`` gets each row as it is
    measured (the check writes it out at once); ``mmcv_unavailable``: why mmcv's op is not compared (e.g.
    its background build failed), put in its column instead."""
    import time

    import torch

    from mssf_blocks.functional.deform.grid import grid_sample_static

    h, w = (64, 96) if smoke else (1216, 1936)
    heads, points = (2, 2) if smoke else (8, 4)
    level_sets = [(4, 8)] if smoke else [(4, 8, 16, 32, 64), (4, 8, 16, 32)]
    # N = 8,000 (the targets' size) first: rows past the budget are the last ones; 4 levels at 8,000 only
    sizes_of = {2: (50,), 5: (8000, 2500, 20000), 4: (8000,)}
    widths = (8,) if smoke else (32, 256)
    # (on CPU tensors the kernels run under Triton's interpreter only: the tests check this stage so)
    triton_ok = device.type == "cuda" or os.environ.get("TRITON_INTERPRET") == "1"
    if triton_ok:
        from mssf_blocks.functional.deform.triton import kernels as tk
    mmcv_fn, mmcv_why = ((None, mmcv_unavailable) if mmcv_unavailable else
                         _mmcv_function(mmcv_src, build_dir or Path("outputs/mmcv_build"))
                         if device.type == "cuda" else (None, "n/a (cpu)"))
    time_it = _timer(device)
    rows = []
    g = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    for strides in level_sets:
        shapes_hw = [(-(-h // s), -(-w // s)) for s in strides]
        numel = [a * b for a, b in shapes_hw]
        shapes = torch.tensor(shapes_hw, dtype=torch.int32, device=device)
        starts = torch.tensor([sum(numel[:i]) for i in range(len(numel))], dtype=torch.int32, device=device)
        for d in widths:
            for dtype in (torch.float32, torch.bfloat16):
                value = torch.randn(1, sum(numel), heads, d, generator=g).to(device, dtype)
                for n in sizes_of[len(strides)]:
                    loc = torch.rand(n, heads, len(strides), points, 2, generator=g).to(device)
                    wt = torch.rand(n, heads, len(strides), points, generator=g).to(device).softmax(-1)
                    idx = torch.zeros(n, dtype=torch.int64, device=device)
                    grad = torch.randn(n, heads, d, generator=g).to(device, dtype)
                    row: Dict[str, object] = dict(levels=len(strides), d=d, dtype=str(dtype).split(".")[-1], N=n)
                    if time.perf_counter() - t0 > budget_s:
                        rows.append(dict(row, grid_fwd_ms=f"skipped (stage budget {budget_s:.0f} s)"))
                        if on_row:
                            on_row(rows[-1])
                        continue

                    def levels_of(v):
                        return [part.view(1, a, b, heads, d).permute(0, 3, 4, 1, 2)
                                for part, (a, b) in zip(v.split(numel, 1), shapes_hw)]

                    # The grid path as MSDFF runs it: lower-precision values read as float32 (grid_sample
                    # would round the locations to the values' dtype: ~4 px on a 1,000-px level in bf16).
                    def grid_fwd():
                        return grid_sample_static(levels_of(value.float()), idx, loc, wt)

                    def grid_fwd_bwd():
                        v = value.detach().requires_grad_()
                        lc, wc = loc.detach().requires_grad_(), wt.detach().requires_grad_()
                        out = grid_sample_static(levels_of(v.float()), idx, lc, wc)
                        out.backward(grad.float())

                    with torch.no_grad():
                        ref = grid_fwd().float()
                    row["grid_fwd_ms"] = 1e3 * time_it(lambda: torch.no_grad()(grid_fwd)(), repeats)
                    row["grid_fwd_bwd_ms"] = 1e3 * time_it(grid_fwd_bwd, repeats)
                    row["grid_MiB"] = _peak(device, grid_fwd_bwd)
                    if triton_ok:
                        def tri_fwd():
                            return tk.deform_sample_forward(value, shapes, starts, idx, loc, wt)

                        def tri_fwd_bwd():
                            tri_fwd()
                            tk.deform_sample_backward(value, shapes, starts, idx, loc, wt, grad, True)

                        row["triton_fwd_ms"] = 1e3 * time_it(tri_fwd, repeats)
                        row["triton_fwd_bwd_ms"] = 1e3 * time_it(tri_fwd_bwd, repeats)
                        row["triton_MiB"] = _peak(device, tri_fwd_bwd)
                        row["triton_max_abs_diff"] = float((tri_fwd().float() - ref).abs().max())
                        row["fwd_bwd_ratio_grid_over_triton"] = row["grid_fwd_bwd_ms"] / row["triton_fwd_bwd_ms"]
                    else:
                        row["triton_fwd_ms"] = "n/a (cpu)"
                    if mmcv_fn is not None:
                        try:
                            shapes64 = shapes.long()
                            starts64 = starts.long()
                            mv, ml, mw = value, loc.to(dtype)[None], wt.to(dtype)[None]

                            def mm_fwd():
                                return mmcv_fn.apply(mv, shapes64, starts64, ml, mw, 64)

                            def mm_fwd_bwd():
                                v = mv.detach().requires_grad_()
                                lc, wc = ml.detach().requires_grad_(), mw.detach().requires_grad_()
                                mmcv_fn.apply(v, shapes64, starts64, lc, wc, 64).backward(grad.reshape(1, n, -1))

                            row["mmcv_fwd_ms"] = 1e3 * time_it(mm_fwd, repeats)
                            row["mmcv_fwd_bwd_ms"] = 1e3 * time_it(mm_fwd_bwd, repeats)
                            row["mmcv_MiB"] = _peak(device, mm_fwd_bwd)
                            row["mmcv_max_abs_diff"] = float((mm_fwd().float().view(n, heads, d) - ref).abs().max())
                        except Exception as exc:  # noqa: BLE001 - e.g. no kernel for this dtype
                            row["mmcv_fwd_ms"] = f"error ({type(exc).__name__}: {str(exc)[:80]})"
                    else:
                        row["mmcv_fwd_ms"] = mmcv_why
                    rows.append(row)
                    if on_row:
                        on_row(row)
                    print(f"  sampling {row}", flush=True)
    return rows
