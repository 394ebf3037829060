"""The floors of ``benchmarks/static_path.py``: how fast any exact static-shape MSDFF could be, measured.

MSDFF's sampling computes, per (voxel, head), ``sum_k w_k (W_m x_k + b_m)`` over the bilinear corners ``k``
of its points on every level. With static shapes (no data-dependent sizes: no set of touched pixels)
an exact formulation has two ways per level, whatever operators build them:

* project first: ``W`` applied to every pixel of the level (the touched ones are data-dependent), then
  ``d = C / M`` channels read per head and corner;
* sample first: the ``C`` raw channels of every corner read (the weights differ per head, so the
  weighted sums come before the projection), then ``W_m`` applied per (voxel, head).

(Projecting each corner's row costs more than either.) So, per level, the cheaper of "project every
pixel" and "read every corner's raw row" is a floor for every static formulation built from these
primitives, and the sum over levels a floor of the whole sampling. Eager MSDFF escapes it by projecting
only the pixels its voxels touch, a data-dependent set.

* **PyTorch** (``torch.export``, ``static_path()``): the primitives are the static path's own, timed on
  the frame's real locations in its blocks of queries (:func:`torch_floor`): ``embedding_bag`` over the
  raw rows of the level (after the copy into a row table that a level not in channels-last memory needs:
  the raw rows of an NCHW level are 256 strided reads each), and the level's projection plus the
  ``d``-channel bags. The floor of the static path = the rest of its
  forward (everything but the sampling call, measured) + the per-level minima.
* **onnxruntime** (operators TensorRT parses; no embedding bag, which ONNX writes as a ``Loop``): per
  level the cheapest of three one-operator graphs built with ``onnx.helper`` (:func:`onnx_floor`): the
  1 x 1 ``Conv`` projecting every pixel, the ``Gather`` of every corner's raw row (its table made by a
  ``Transpose``, as an NCHW level needs), or one ``GridSample`` of the raw level at every point (the
  four corners blended inside the operator). Each graph ends in a ``ReduceSum`` so that nothing large is
  copied out. Nothing else of MSDFF is counted, so the floor is low.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from typing import Callable, Dict, List

import torch

from _common import measure
from mssf_blocks.functional.deform import bag
from mssf_blocks.samplers import msdff as msdff_module

__all__ = ["capture_static_sampling", "onnx_floor", "torch_floor"]


def _cpu(fn: Callable[[], object], repeats: int) -> float:
    """Median process CPU time (s) of ``repeats`` calls after a warm-up (``_common.measure``)."""
    return measure(fn, repeats, clock=time.process_time)[0]


@contextmanager
def _recording(module, name: str, record: List):
    """Replace ``module.name`` by a wrapper appending its ``(args, kwargs)`` to ``record``."""
    original = getattr(module, name)

    def wrapper(*args, **kwargs):
        record.append((args, kwargs))
        return original(*args, **kwargs)

    setattr(module, name, wrapper)
    try:
        yield
    finally:
        setattr(module, name, original)


def capture_static_sampling(run_static: Callable[[], object]) -> tuple:
    """The arguments ``(levels, image_index, locations, weights, proj_weight, proj_bias)`` with which the
    static path's forward ``run_static`` calls ``bag.sample_project_static`` (MSDFF's only one)."""
    record: List = []
    with torch.no_grad(), _recording(msdff_module.bag, "sample_project_static", record):
        run_static()
    if len(record) != 1:
        raise SystemExit(f"internal error: expected one static sampling call, got {len(record)}")
    return record[0][0]


def _ordered(args: tuple) -> tuple:
    """``args`` with the queries in the static path's row order (as it bags them)."""
    levels, image_index, locations, weights, w, b = args
    order = bag._row_order(image_index, locations, [tuple(lv.shape[-2:]) for lv in levels])
    return levels, image_index[order], locations[order], weights[order], w, b


def _blocks(image_index, locations, weights, channels: int) -> List[tuple]:
    """``(image_index, locations, weights)`` of the queries in the static path's blocks (``bag.static_blocks``)."""
    q, m = locations.shape[:2]
    k = bag.static_blocks(q, m, channels, locations.element_size())
    return list(zip(image_index.tensor_split(k), locations.tensor_split(k), weights.tensor_split(k)))


def torch_floor(args: tuple, repeats: int) -> Dict[str, object]:
    """``{"sampling": s, "floor": s, "levels": [(raw, projected), ...]}``: the static path's sampling call on
    ``args`` (:func:`capture_static_sampling`) and its floor, the sum over levels of the cheaper of the
    level's raw-row bags alone and its projection plus ``d``-channel bags alone, bagged in the static path's
    blocks of queries (process CPU time)."""
    levels, image_index, locations, weights, w, b = _ordered(args)
    blocks = _blocks(image_index, locations, weights, levels[0].shape[2])
    per_level = []
    with torch.no_grad():
        sampling = _cpu(lambda: bag.sample_project_static(*args), repeats)
        for i, lvl in enumerate(levels):
            def raw(lvl=lvl, i=i):
                table = bag._row_major(lvl)  # (free for channels-last levels, a layout copy of NCHW ones)
                for ii, loc, wt in blocks:
                    bag.sample([table], ii, loc[:, :, i : i + 1], wt[:, :, i : i + 1], True, query_major=True)

            def projected(lvl=lvl, i=i):
                table = bag._project_level(lvl, w, b)
                for ii, loc, wt in blocks:
                    bag.sample([table], ii, loc[:, :, i : i + 1], wt[:, :, i : i + 1], False, query_major=True)

            per_level.append((_cpu(raw, repeats), _cpu(projected, repeats)))
    return {"sampling": sampling, "floor": sum(min(r, p) for r, p in per_level), "levels": per_level}


def _corner_rows(args: tuple) -> List[torch.Tensor]:
    """Per level, the ``(Q * M, 4 * P)`` raw-table rows of every corner, as the static path bags them
    (recorded from ``bag.sample`` on that level alone)."""
    levels, image_index, locations, weights, _, _ = _ordered(args)
    rows = []
    for i, lvl in enumerate(levels):
        record: List = []
        with torch.no_grad(), _recording(bag.torch_versions, "embedding_bag", record):
            bag.sample([lvl], image_index, locations[:, :, i : i + 1], weights[:, :, i : i + 1], False,
                       query_major=True)
        rows.append(record[0][0][0].to(torch.int64))
    return rows


def _session(graph, repeats: int, feeds: Dict[str, "object"], expected: tuple) -> float:
    """onnxruntime's median time for ``graph`` on ``feeds``, after checking its output against ``expected``:
    ``(sum, sum of magnitudes)`` of the same elements in float64 PyTorch (the graph does the work it stands
    for; onnxruntime's float32 sums of 10^8 elements drift by about 1e-6 of the magnitudes, a wrong row or weight
    by about the square root of the count, 1e-4 of them and more)."""
    import onnx
    import onnxruntime as ort

    model = onnx.helper.make_model(graph, opset_imports=[onnx.helper.make_opsetid("", 18)])
    onnx.checker.check_model(model)
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1
    session = ort.InferenceSession(model.SerializeToString(), opts, providers=["CPUExecutionProvider"])
    got = float(session.run(None, feeds)[0])
    want, magnitude = (float(t) for t in expected)
    if abs(got - want) > 1e-5 * magnitude + 1e-3:
        raise SystemExit(f"internal error: the floor graph {graph.name!r} gave {got}, expected {want}")
    return _cpu(lambda: session.run(None, feeds), repeats)


def onnx_floor(args: tuple, repeats: int) -> Dict[str, object]:
    """``{"floor": s, "levels": [(conv, gather, grid_sample), ...]}``: per level, onnxruntime's time (one
    thread, process CPU time) for each of the three one-operator graphs of the module docstring on the
    frame's real corners (``args`` from :func:`capture_static_sampling`); the floor sums the minima."""
    from onnx import TensorProto
    from onnx import helper as oh

    levels, image_index, locations, _, w, _ = _ordered(args)
    m, d, c = w.shape
    rows = _corner_rows(args)
    out = oh.make_tensor_value_info("out", TensorProto.FLOAT, [])
    per_level = []
    for i, lvl in enumerate(levels):
        nchw = lvl[:, 0].contiguous().numpy()  # (I, C, H, W)
        x = oh.make_tensor_value_info("x", TensorProto.FLOAT, list(nchw.shape))
        weight = oh.make_tensor("w", TensorProto.FLOAT, [m * d, c, 1, 1], w.reshape(-1).tolist())
        conv = oh.make_graph([oh.make_node("Conv", ["x", "w"], ["y"]),
                              oh.make_node("ReduceSum", ["y"], ["out"], keepdims=0)], "project", [x], [out], [weight])
        idx = rows[i].reshape(-1).numpy()
        gather = oh.make_graph([
            oh.make_node("Transpose", ["x"], ["t"], perm=[0, 2, 3, 1]),
            oh.make_node("Reshape", ["t", "shape"], ["table"]),
            oh.make_node("Gather", ["table", "idx"], ["g"], axis=0),
            oh.make_node("ReduceSum", ["g"], ["out"], keepdims=0),
        ], "gather", [x, oh.make_tensor_value_info("idx", TensorProto.INT64, list(idx.shape))], [out],
            [oh.make_tensor("shape", TensorProto.INT64, [2], [-1, c])])
        # every point of the level as one grid row per image: (I, Q_i * M, P, 2) in [-1, 1], align_corners=0
        loc = locations[:, :, i].reshape(-1, locations.shape[3], 2)
        grid_points = (loc * 2.0 - 1.0).unsqueeze(0).numpy()
        if nchw.shape[0] != 1:
            raise SystemExit("internal error: the ONNX floor is measured on one image")
        g = oh.make_tensor_value_info("g", TensorProto.FLOAT, list(grid_points.shape))
        sample = oh.make_graph([
            oh.make_node("GridSample", ["x", "g"], ["s"], mode="bilinear", padding_mode="zeros", align_corners=0),
            oh.make_node("ReduceSum", ["s"], ["out"], keepdims=0),
        ], "grid_sample", [x, g], [out])
        with torch.no_grad():
            x64, w64 = lvl[:, 0].double(), w.double().reshape(m * d, c)
            table = x64.permute(0, 2, 3, 1).reshape(-1, c)
            r = rows[i].reshape(-1)
            g64 = torch.from_numpy(grid_points).double()

            def sampled(t):
                return torch.nn.functional.grid_sample(t, g64, mode="bilinear", padding_mode="zeros",
                                                       align_corners=False).sum()

            expected = ((w64.sum(0) @ table.sum(0), w64.abs().sum(0) @ table.abs().sum(0)),
                        (table.sum(1)[r].sum(), table.abs().sum(1)[r].sum()),
                        (sampled(x64), sampled(x64.abs())))
        per_level.append((_session(conv, repeats, {"x": nchw}, expected[0]),
                          _session(gather, repeats, {"x": nchw, "idx": idx}, expected[1]),
                          _session(sample, repeats, {"x": nchw, "g": grid_points}, expected[2])))
    return {"floor": sum(min(t) for t in per_level), "levels": per_level}

