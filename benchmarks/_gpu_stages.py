"""Stages 2 and 3 of ``benchmarks/gpu_check.py``, the measurements on the device: the MSDFF benchmark
(the reference formulation against ours on VoD shapes, forward and forward+backward, float32 and bf16
autocast) and one training step per example detector (float32, bf16 and fp16 autocast). Times are
CUDA-event medians after a warm-up (the median of ``_common.measure`` on the CPU), memory is the
peak ``torch.cuda.max_memory_allocated`` over the allocation before the call.

Split from ``gpu_check.py`` (one concept per file); torch and the library are imported inside the
functions, after ``gpu_check`` has made sure they are installed.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Optional

__all__ = ["STRIDES", "msdff_benchmark", "detector_steps"]


# --------------------------------------------------------------------------------------------------
# 2. MSDFF: reference vs ours
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


def msdff_benchmark(device, smoke: bool, repeats: int) -> List[Dict[str, object]]:
    """Reference (project every pixel + grid_sample) vs ours (method="auto") on VoD shapes."""
    import torch

    from mssf_blocks.fusion import MSDFF
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
        uv = torch.rand(n, 1, 2, generator=g)
        proj = CentroidProjection(uv=uv.to(device), depth=torch.ones(n, 1, device=device),
                                  valid=torch.ones(n, 1, dtype=torch.bool, device=device),
                                  centroid=torch.zeros(n, 3, device=device),
                                  has_points=torch.ones(n, dtype=torch.bool, device=device),
                                  batch_index=torch.zeros(n, dtype=torch.long, device=device))
        query = torch.randn(n, embed, generator=g).to(device)
        torch.manual_seed(0)
        ref = MSDFF(embed, channels, num_heads=heads, num_levels=len(strides), num_points=points,
                    method="reference", value_projection="before_sampling").to(device).train()
        ours = MSDFF(embed, channels, num_heads=heads, num_levels=len(strides), num_points=points,
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
            print(f"  MSDFF N={n} {row['precision']}: fwd ratio {row['fwd_ratio']:.2f}, fwd+bwd ratio "
                  f"{row['fwd_bwd_ratio']:.2f}, max |diff| {diff:.2e}", flush=True)
    return rows


class _null:
    def __enter__(self):
        return None

    def __exit__(self, *exc):
        return False


# --------------------------------------------------------------------------------------------------
# 3. one training step per detector
# --------------------------------------------------------------------------------------------------
def detector_steps(device, smoke: bool, repeats: int) -> List[Dict[str, object]]:
    import torch

    from mssf_blocks import _compat
    from mssf_examples.data import RadarCameraBatch
    from mssf_examples.detectors import DETECTOR_NAMES, build_detector
    from mssf_examples.presets import TINY, VOD
    from mssf_examples.spconv_compat import enable_cpu_backward

    enable_cpu_backward()
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
    time_it = _timer(device)
    rows = []
    for name in DETECTOR_NAMES:
        row: Dict[str, object] = dict(detector=name, fusion_blocks=2)
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

            row["step_ms"] = time_it(step, repeats) * 1e3
            row["peak_MiB"] = _peak(device, step)
            row["loss_finite"] = bool(torch.isfinite(step()).item())
        except Exception as exc:  # noqa: BLE001 - the report says what failed, the other detectors still run
            row["error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
        # the same step under autocast (what --amp bf16 / fp16 run; spconv on CUDA is the open question)
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
                row[f"{tag}_step_ms"] = time_it(lambda: step(dtype), repeats) * 1e3
                row[f"{tag}_loss_finite"] = bool(torch.isfinite(step(dtype)).item())
            except Exception as exc:  # noqa: BLE001
                row[f"{tag}_step_ms"] = f"{type(exc).__name__}: {str(exc)[:120]}"
        rows.append(row)
        print(f"  {name}: " + (f"{row['step_ms']:.1f} ms/step" if "step_ms" in row else row["error"]), flush=True)
    return rows
