"""Stages (c) and (d) of ``benchmarks/gpu_check.py``, measurements on the device: the MSDFF benchmark
(the reference formulation against ours on VoD shapes, forward and forward+backward, float32 and bf16
autocast) and per example detector one training step (float32, bf16 and fp16 autocast) and the
inference latency (float32, bf16 autocast) at a VoD frame. Times are
CUDA-event medians after a warm-up (the median of ``_common.measure`` on the CPU), memory is the
peak ``torch.cuda.max_memory_allocated`` over the allocation before the call.

Split from ``gpu_check.py`` (one concept per file); torch and the library are imported inside the
functions, after ``gpu_check`` has made sure they are installed.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Optional

__all__ = ["STRIDES", "msdff_benchmark", "detector_steps", "vod_batch"]


# --------------------------------------------------------------------------------------------------
# (c) MSDFF: reference vs ours
# --------------------------------------------------------------------------------------------------
STRIDES = (4, 8, 16, 32, 64)


def _timer(device) -> Callable[[Callable[[], object], int], float]:
    import torch

    def cuda_time(fn, repeats):
        fn()  # warm-up
        torch.cuda.synchronize(device)
        times = []
        for _ in range(repeats):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            torch.cuda.synchronize(device)
            times.append(a.elapsed_time(b) / 1e3)
        return sorted(times)[len(times) // 2]

    def cpu_time(fn, repeats):
        from _common import measure  # benchmarks/ is the script's folder

        return measure(fn, repeats)[0]  # median wall time after one warm-up call

    return cuda_time if device.type == "cuda" else cpu_time


def _peak(device, fn) -> Optional[float]:
    import torch

    if device.type != "cuda":
        return None
    torch.cuda.synchronize(device)
    torch.cuda.reset_peak_memory_stats(device)
    base = torch.cuda.memory_allocated(device)
    fn()
    torch.cuda.synchronize(device)
    return (torch.cuda.max_memory_allocated(device) - base) / 2**20


def _past(deadline: Optional[float]) -> bool:
    import time

    return deadline is not None and time.perf_counter() > deadline


def msdff_benchmark(device, smoke: bool, repeats: int, deadline: Optional[float] = None,
                    on_row: Optional[Callable[[Dict[str, object]], None]] = None) -> List[Dict[str, object]]:
    """Reference (project every pixel + grid_sample) vs ours (method="auto") on VoD shapes; rows started
    after ``deadline`` (a ``time.perf_counter()`` value) are listed as skipped; ``on_row`` gets each row."""
    import torch

    from mssf_blocks.samplers import MSDFF
    from mssf_blocks.geometry import CentroidProjection

    h, w = (64, 96) if smoke else (1216, 1952)
    strides = STRIDES[:2] if smoke else STRIDES
    channels, heads, points, embed = (16, 2, 2, 8) if smoke else (256, 8, 4, 64)
    sizes = (50, 200) if smoke else (2500, 8000, 40000)
    g = torch.Generator().manual_seed(0)
    feats = [torch.randn(1, channels, -(-h // s), -(-w // s), generator=g).to(device) for s in strides]
    time_it = _timer(device)
    rows = []
    for n in sizes:
        if _past(deadline):
            rows.append(dict(N=n, skipped="past the stage's time budget"))
            if on_row:
                on_row(rows[-1])
            continue
        uv = torch.rand(n, 1, 2, generator=g)
        proj = CentroidProjection(uv=uv.to(device), depth=torch.ones(n, 1, device=device),
                                  valid=torch.ones(n, 1, dtype=torch.bool, device=device),
                                  centroid=torch.zeros(n, 3, device=device),
                                  has_points=torch.ones(n, dtype=torch.bool, device=device),
                                  batch_index=torch.zeros(n, dtype=torch.long, device=device))
        query = torch.randn(n, embed, generator=g).to(device)
        torch.manual_seed(0)
        ref = MSDFF(channels, embed, num_heads=heads, num_levels=len(strides), num_points=points,
                    method="reference", value_projection="before_sampling").to(device).train()
        ours = MSDFF(channels, embed, num_heads=heads, num_levels=len(strides), num_points=points,
                     method="auto").to(device).train()
        ours.load_state_dict(ref.state_dict())
        for amp in ("float32", "bfloat16"):
            if amp == "bfloat16" and device.type == "cuda" and not torch.cuda.is_bf16_supported():
                continue
            ctx = (lambda: torch.autocast(device.type, dtype=torch.bfloat16)) if amp == "bfloat16" else None
            row: Dict[str, object] = dict(N=n, precision=amp if amp == "float32" else "bf16 autocast")

            def fwd(mod):
                def f():
                    with torch.no_grad(), (ctx() if ctx else _null()):
                        return mod(query, feats, proj)
                return f

            def fwd_bwd(mod):
                q = query.clone().requires_grad_(True)

                def f():
                    with ctx() if ctx else _null():
                        out = mod(q, feats, proj)
                    out.float().sum().backward()
                return f

            with torch.no_grad(), (ctx() if ctx else _null()):
                diff = (ref(query, feats, proj).float() - ours(query, feats, proj).float()).abs().max().item()
            row["max_abs_diff"] = diff
            for kind, make in (("fwd", fwd), ("fwd_bwd", fwd_bwd)):
                t_ref, t_ours = time_it(make(ref), repeats), time_it(make(ours), repeats)
                row[f"{kind}_ref_ms"], row[f"{kind}_ours_ms"] = t_ref * 1e3, t_ours * 1e3
                row[f"{kind}_ratio"] = t_ref / t_ours
                m_ref, m_ours = _peak(device, make(ref)), _peak(device, make(ours))
                row[f"{kind}_ref_MiB"], row[f"{kind}_ours_MiB"] = m_ref, m_ours
            rows.append(row)
            if on_row:
                on_row(row)
            print(f"  MSDFF N={n} {row['precision']}: fwd ratio {row['fwd_ratio']:.2f}, fwd+bwd ratio "
                  f"{row['fwd_bwd_ratio']:.2f}, max |diff| {diff:.2e}", flush=True)
    return rows


class _null:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


# --------------------------------------------------------------------------------------------------
# (d) per detector: a training step and the inference latency
# --------------------------------------------------------------------------------------------------
def vod_batch(device, smoke: bool):
    """A VoD-sized synthetic frame (smoke: the TINY preset's): 2,500 radar points in the preset's range, one
    1216 x 1936 camera, one ground-truth car; and the preset."""
    import torch

    from mssf_examples.data.batch import RadarCameraBatch
    from mssf_examples.models.presets import TINY, VOD

    preset = TINY if smoke else VOD
    h, w = (32, 64) if smoke else (1216, 1936)
    g = torch.Generator().manual_seed(0)
    x0, y0, z0, x1, y1, z1 = preset.point_cloud_range
    num_points = 300 if smoke else 2500
    lo, hi = torch.tensor([x0, y0, z0]), torch.tensor([x1, y1, z1])
    xyz = lo + torch.rand(num_points, 3, generator=g) * (hi - lo) * 0.999
    pts = torch.cat([xyz, torch.randn(num_points, preset.num_point_features - 3, generator=g)], 1)
    l2i = torch.zeros(1, 1, 3, 4)
    l2i[0, 0, 0, 1], l2i[0, 0, 1, 2], l2i[0, 0, 2, 0] = -w / 2, -w / 2, 1.0
    l2i[0, 0, 0, 0], l2i[0, 0, 1, 0] = w / 2, h / 2
    cx = (x0 + x1) / 2
    box = torch.tensor([[max(cx, 5.0), 0.0, -0.5, 3.9, 1.6, 1.56, 0.3]])
    batch = RadarCameraBatch(points=[pts], lidar2img=l2i, images=torch.rand(1, 1, 3, h, w, generator=g),
                             gt_boxes=[box], gt_labels=[torch.tensor([0])]).to(device)
    return batch, preset


def _spconv_or_stand_in() -> Optional[str]:
    """``None`` when spconv imports; else why not, after putting a stand-in ``spconv.pytorch`` module in
    ``sys.modules`` so that the examples' detector module (which imports spconv at module level for the
    voxel backbones) imports and MSSF-PointPillars (pure torch) still runs; the spconv detectors then fail
    at construction and their rows say why."""
    try:
        import spconv.pytorch  # noqa: F401

        return None
    except Exception as exc:  # noqa: BLE001 - ImportError, or an OSError of its compiled libraries
        why = f"spconv does not import: {type(exc).__name__}: {str(exc)[:200]}"
    import sys
    import types

    import torch

    def missing(*args, **kwargs):
        raise ImportError(why)

    stand_in = types.ModuleType("spconv.pytorch")
    stand_in.SparseModule = torch.nn.Module
    for name in ("SparseSequential", "SubMConv3d", "SparseConv3d", "SubMConv2d", "SparseConv2d", "SparseConvTensor",
                 "SparseInverseConv3d", "SparseMaxPool3d", "ToDense"):
        setattr(stand_in, name, type(name, (torch.nn.Module,), {"__init__": missing}))
    parent = sys.modules.get("spconv") or types.ModuleType("spconv")
    parent.pytorch = stand_in
    sys.modules.update({"spconv": parent, "spconv.pytorch": stand_in})
    return why


def detector_steps(device, smoke: bool, repeats: int, deadline: Optional[float] = None,
                   on_row: Optional[Callable[[Dict[str, object]], None]] = None) -> List[Dict[str, object]]:
    """Per detector (MSSF-PointPillars first: pure torch), one training step (forward + backward + AdamW)
    and the inference latency (eval, no_grad, decoding included), in float32 and under bf16 autocast (and
    the training step under fp16 autocast); peak memory. Detectors started after ``deadline`` are listed
    as skipped; ``on_row`` gets each row as it is measured."""
    import torch

    spconv_missing = _spconv_or_stand_in()
    from mssf_blocks import torch_versions as _compat
    from mssf_examples.models.detectors import DETECTOR_NAMES, build_detector
    from mssf_examples.models.spconv_helpers import enable_cpu_backward

    if spconv_missing is None:
        enable_cpu_backward()
    batch, preset = vod_batch(device, smoke)
    time_it = _timer(device)
    rows = []
    names = ["pointpillars"] + [n for n in DETECTOR_NAMES if n != "pointpillars"]
    for name in names:
        row: Dict[str, object] = dict(detector=name, fusion_blocks=2)
        if _past(deadline):
            row["error"] = "skipped: past the stage's time budget"
            rows.append(row)
            if on_row:
                on_row(row)
            continue
        try:
            torch.manual_seed(0)
            model = build_detector(name, preset, num_fusion_blocks=2).to(device).train()
            opt = torch.optim.AdamW([p for p in model.parameters() if p.requires_grad], lr=1e-4)

            def step(dtype=None):
                opt.zero_grad(set_to_none=True)
                with torch.autocast(device.type, dtype=dtype) if dtype is not None else _null():
                    loss = model(batch)["loss"]
                loss.backward()
                opt.step()
                return loss

            def infer(dtype=None):
                with torch.no_grad(), torch.autocast(device.type, dtype=dtype) if dtype is not None else _null():
                    return model(batch)

            row["step_ms"] = time_it(step, repeats) * 1e3
            row["peak_MiB"] = _peak(device, step)
            row["loss_finite"] = bool(torch.isfinite(step()).item())
            model.eval()
            row["infer_ms"] = time_it(infer, repeats) * 1e3
            row["infer_fps"] = 1e3 / row["infer_ms"]
            row["infer_MiB"] = _peak(device, infer)
            model.train()
        except Exception as exc:  # noqa: BLE001 - the report says what failed, the other detectors still run
            row["error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
            if spconv_missing and name != "pointpillars":
                row["error"] = spconv_missing
        # the same under autocast (what --amp bf16 / fp16 run; spconv on CUDA is the open question)
        for tag, dtype in (("bf16", torch.bfloat16), ("fp16", torch.float16)):
            if "error" in row:
                break
            if device.type == "cpu" and name != "pointpillars":
                row[f"{tag}_step_ms"] = "n/a (spconv CPU)"
                continue
            if device.type == "cpu" and dtype == torch.float16 and _compat.missing("cpu_float16_autocast"):
                row[f"{tag}_step_ms"] = f"n/a ({_compat.missing('cpu_float16_autocast')})"
                continue
            try:
                if tag == "bf16":  # the same parameters, the loss in float32 and under bf16 autocast
                    with torch.no_grad():
                        ref = float(model(batch)["loss"])
                        with torch.autocast(device.type, dtype=dtype):
                            low = float(model(batch)["loss"])
                    row["bf16_loss_rel_diff"] = abs(low - ref) / max(abs(ref), 1e-12)
                    model.eval()
                    row["bf16_infer_ms"] = time_it(lambda: infer(dtype), repeats) * 1e3
                    model.train()
                row[f"{tag}_step_ms"] = time_it(lambda: step(dtype), repeats) * 1e3
                row[f"{tag}_loss_finite"] = bool(torch.isfinite(step(dtype)).item())
            except Exception as exc:  # noqa: BLE001
                model.train()
                row[f"{tag}_step_ms"] = f"{type(exc).__name__}: {str(exc)[:120]}"
        rows.append(row)
        if on_row:
            on_row(row)
        print(f"  {name}: " + (f"{row['step_ms']:.1f} ms/step, {row['infer_ms']:.1f} ms/frame" if "infer_ms" in row
                               else row["error"]), flush=True)
    return rows
