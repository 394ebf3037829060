"""Stage (c) of ``benchmarks/gpu_check.py``, second part: one FusionBlock at the paper's width on its real input.

The block is MSSF-PointPillars' first fusion block (VoD preset: MSDFF with ``value_proj`` 256 -> 256 over
the four FPN levels of a 1216 x 1936 image, 8 heads, 4 points, the query initialisation and the voxels'
centroids; pure torch, no spconv), and its input is the one it gets inside the detector on the check's
VoD-sized frame (captured with a forward pre-hook during one forward of the detector). Timed alone:
forward (no_grad) and forward + backward (the voxel features and the block's parameters), float32 and
bf16 autocast, peak memory, and the bf16 output's largest difference from the float32 one.

Split from ``_gpu_stages.py`` (one concept per file).
"""

from __future__ import annotations

from typing import Callable, Dict, List, Optional

from _gpu_stages import _null, _past, _peak, _timer, vod_batch  # benchmarks/ (the script's folder) is on sys.path

__all__ = ["fusion_block_benchmark"]


def fusion_block_benchmark(device, smoke: bool, repeats: int, deadline: Optional[float] = None,
                           on_row: Optional[Callable[[Dict[str, object]], None]] = None) -> List[Dict[str, object]]:
    import torch

    rows: List[Dict[str, object]] = []

    def emit(row):
        rows.append(row)
        if on_row:
            on_row(row)

    try:
        from _gpu_stages import _spconv_or_stand_in

        _spconv_or_stand_in()  # (the examples' detector module imports spconv; PointPillars does not use it)
        from mssf_blocks.blocks import FusionBlock
        from mssf_examples.models.detectors import build_detector

        batch, preset = vod_batch(device, smoke)
        torch.manual_seed(0)
        model = build_detector("pointpillars", preset, num_fusion_blocks=2).to(device).train()
        block = next(m for m in model.modules() if isinstance(m, FusionBlock))
        seen = {}
        handle = block.register_forward_pre_hook(lambda mod, args, kwargs: seen.setdefault("in", (args, kwargs)),
                                                 with_kwargs=True)
        with torch.no_grad():
            model(batch)
        handle.remove()
        args, kwargs = seen["in"]
    except Exception as exc:  # noqa: BLE001 - reported in the row; the later stages still run
        emit(dict(block="pointpillars.fusion[0]", error=f"{type(exc).__name__}: {str(exc)[:300]}"))
        return rows
    x = args[0]
    time_it = _timer(device)

    def run(dtype, grad: bool):
        feats = x.features.detach().requires_grad_(grad)
        xin = x.replace(features=feats) if hasattr(x, "replace") else x.replace_feature(feats)
        with torch.autocast(device.type, dtype=dtype) if dtype is not None else _null():
            out = block(xin, *args[1:], **kwargs)
        out = out[0] if isinstance(out, tuple) else out
        return out.features

    ref = None
    for precision, dtype in (("float32", None), ("bf16 autocast", torch.bfloat16)):
        row: Dict[str, object] = dict(block=f"pointpillars.fusion[0] ({type(block.fusion).__name__}, value "
                                             f"{getattr(block.fusion, 'value_channels', '?')} ch)", voxels=int(x.features.shape[0]),
                                      precision=precision)
        if _past(deadline):
            emit(dict(row, skipped="past the stage's time budget"))
            continue
        try:
            def fwd():
                with torch.no_grad():
                    return run(dtype, False)

            def fwd_bwd():
                run(dtype, True).float().sum().backward()

            out = fwd().float()
            ref = out if ref is None else ref
            row["max_abs_diff_vs_fp32"] = float((out - ref).abs().max()) if out.numel() else 0.0
            row["fwd_ms"] = 1e3 * time_it(fwd, repeats)
            row["fwd_bwd_ms"] = 1e3 * time_it(fwd_bwd, repeats)
            row["fwd_bwd_MiB"] = _peak(device, fwd_bwd)
        except Exception as exc:  # noqa: BLE001
            row["error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
        emit(row)
        print(f"  FusionBlock {row}", flush=True)
    return rows
