"""The report of ``benchmarks/gpu_check.py``: ``gpu_check.json`` and ``gpu_check.md``, rewritten after every
row a stage produces, so that a run stopped at its time limit (the device call's, or the check's own
watchdog) still leaves everything it measured in the output folder.

Split from ``gpu_check.py`` (one concept per file).
"""

from __future__ import annotations

import json
import os
import threading
from pathlib import Path
from typing import Dict, List

__all__ = ["Report", "markdown"]

#: Report sections: (key, title, columns), in the check's stage order.
SECTIONS = (
    ("sampling", "(b) Sampling core: Triton op, grid path, mmcv's op (fwd+bwd ratio > 1: Triton faster)",
     ["levels", "d", "dtype", "N", "grid_fwd_ms", "triton_fwd_ms", "mmcv_fwd_ms", "grid_fwd_bwd_ms", "triton_fwd_bwd_ms",
      "mmcv_fwd_bwd_ms", "fwd_bwd_ratio_grid_over_triton", "grid_MiB", "triton_MiB", "mmcv_MiB", "triton_max_abs_diff",
      "mmcv_max_abs_diff"]),
    ("msdff", "(c) MSDFF, reference / ours (ratio > 1: ours faster)",
     ["N", "precision", "fwd_ref_ms", "fwd_ours_ms", "fwd_ratio", "fwd_bwd_ref_ms", "fwd_bwd_ours_ms", "fwd_bwd_ratio",
      "fwd_bwd_ref_MiB", "fwd_bwd_ours_MiB", "max_abs_diff", "skipped"]),
    ("fusion_block", "(c) A FusionBlock (MSSF-PointPillars' first, MSDFF, paper width) on its VoD-frame input",
     ["block", "voxels", "precision", "fwd_ms", "fwd_bwd_ms", "fwd_bwd_MiB", "max_abs_diff_vs_fp32", "error",
      "skipped"]),
    ("detectors", "(d) Each detector at a VoD frame (n = 2 MSDFF blocks): training step and inference",
     ["detector", "step_ms", "peak_MiB", "loss_finite", "infer_ms", "infer_fps", "infer_MiB", "bf16_step_ms",
      "bf16_loss_finite", "bf16_loss_rel_diff", "bf16_infer_ms", "fp16_step_ms", "fp16_loss_finite", "error"]),
)


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e-2 else f"{v:.2f}"
    return str(v).replace("|", "/").replace("\n", " ")


def _table(rows: List[Dict[str, object]], cols: List[str]) -> str:
    cols = [c for c in cols if any(c in r for r in rows)]  # (columns no row has, e.g. skipped, are left out)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def markdown(result: Dict[str, object]) -> str:
    env = result.get("environment", {})
    parts = ["# GPU check", "", "Environment: " + ", ".join(f"{k} {v}" for k, v in env.items()), "",
             "Packages: " + ", ".join(f"{k} {v}" for k, v in result.get("packages", {}).items()), ""]
    b = result.get("bundle")
    if b:
        files = b.get("error") or ", ".join(str(e["file"]) for e in b.get("installed", []))
        parts += [f"Bundle: {files}"
                  + (f" into {b['target']} in {b['seconds']} s" if "seconds" in b else "")
                  + ("; left out: " + "; ".join(b["left_out"]) if b.get("left_out") else ""), ""]
    stages = result.get("stages", {})
    if stages:
        parts += ["Stages: " + ", ".join(f"{k} {v}" for k, v in stages.items()), ""]
    t = result.get("tests")
    if t:
        parts += ["## (a) Tests on the device", "",
                  f"`{t['command']}`: {t['summary']} (exit {t['returncode']}, {t['seconds']:.0f} s)", ""]
        parts += [f"- {f}" for f in t["failures"]] + [f"- {s}" for s in t["host_syncs"]] + [""]
    for key, title, cols in SECTIONS:
        if result.get(key):
            parts += [f"## {title}", "", _table(result[key], cols), ""]
    mm = result.get("mmdet3d")
    if mm:
        parts += ["## (e) The shipped mmdet3d config, trained through our entry", "",
                  _table([mm], ["config", "iters", "iter_s", "loss", "loss_finite", "wall_s", "skipped", "error"]), ""]
    if result.get("stopped"):
        parts += [f"**Stopped:** {result['stopped']}", ""]
    if "seconds" in result:
        parts += [f"Total {result['seconds']:.0f} s."]
    return "\n".join(parts) + "\n"


class Report:
    """The result dict, written to ``<out>/gpu_check.json`` and ``.md`` at every change (atomically:
    a kill between two writes leaves the previous complete file)."""

    def __init__(self, out: Path, **fields) -> None:
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.result: Dict[str, object] = dict(fields)
        self._lock = threading.Lock()  # (the watchdog's thread may write while the stages do)
        self.save()

    def set(self, key: str, value) -> None:
        self.result[key] = value
        self.save()

    def row(self, key: str):
        """A callback appending one row to the list ``key`` and saving."""
        rows = self.result.setdefault(key, [])

        def add(row: Dict[str, object]) -> None:
            rows.append(row)
            self.save()

        return add

    def save(self) -> None:
        with self._lock:
            for name, text in (("gpu_check.json", json.dumps(self.result, indent=1, default=str)),
                               ("gpu_check.md", markdown(self.result))):
                tmp = self.out / (name + ".tmp")
                tmp.write_text(text)
                os.replace(tmp, self.out / name)
