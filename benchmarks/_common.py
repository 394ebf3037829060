"""Timing and peak-memory helpers shared by the benchmark scripts.

Time: one warm-up call, then the median wall time of ``repeats`` calls (the machine is shared, so
the median, not the mean or the minimum).

Peak extra memory: the rise of the process's resident-set high-water mark (Linux ``VmHWM``, reset
through ``/proc/self/clear_refs`` before each call) over the resident size just before the call.
``tracemalloc`` does not see PyTorch's C++ allocations, and the CPU allocator has no peak counter, so
we ask the kernel. To make that honest, :func:`reexec_with_mmap_threshold` re-executes the script with
``MALLOC_MMAP_THRESHOLD_=65536``: glibc then serves every allocation above 64 KiB with ``mmap`` and
unmaps it on free, so freed heap is not silently reused across calls and the high-water mark counts
what a call really allocates (tensors kept alive from before the call do not count).
"""

from __future__ import annotations

import gc
import json
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Dict, List, Sequence, Tuple

__all__ = ["reexec_with_mmap_threshold", "measure", "print_table", "round_spread", "write_json"]

_ENV = "MALLOC_MMAP_THRESHOLD_"


def reexec_with_mmap_threshold(threshold: int = 65536) -> None:
    """Re-execute the running script with ``MALLOC_MMAP_THRESHOLD_`` set (no-op once set)."""
    if os.environ.get(_ENV) is None and sys.platform.startswith("linux"):
        env = dict(os.environ, **{_ENV: str(threshold)})
        os.execve(sys.executable, [sys.executable] + sys.argv, env)


def _proc_kb(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def measure(fn: Callable[[], object], repeats: int = 5, warmup: int = 1,
            clock: Callable[[], float] = time.perf_counter) -> Tuple[float, float]:
    """Median time (s; wall time, or ``clock=time.process_time`` for the process CPU time, the work
    done with one thread and robust to other processes) over ``repeats`` calls after ``warmup``
    calls, and peak extra RSS (MiB).

    The peak is the largest over the repeats of ``VmHWM - VmRSS(before)``; the call's return value
    is dropped after the measurement (so an output it allocates counts).
    """
    for _ in range(warmup):
        fn()
    times: List[float] = []
    peaks: List[float] = []
    for _ in range(repeats):
        gc.collect()
        Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
        before = _proc_kb("VmRSS")
        t0 = clock()
        out = fn()
        times.append(clock() - t0)
        peaks.append((_proc_kb("VmHWM") - before) / 1024.0)
        del out
    return statistics.median(times), max(peaks)


def round_spread(numerators: Sequence[float], denominators: Sequence[float]) -> str:
    """``"lo-hi"``: the lowest and highest per-round ratio of two timings taken in the same interleaved
    rounds (round ``i``'s two calls ran back to back), the spread that the ratio of their medians hides."""
    per_round = [a / b for a, b in zip(numerators, denominators, strict=True)]
    return f"{min(per_round):.2f}-{max(per_round):.2f}"


def print_table(rows: Sequence[Dict[str, object]], columns: Sequence[str]) -> str:
    """Markdown table of ``rows`` (floats with 3 significant digits); printed and returned."""

    def fmt(v: object) -> str:
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    text = "\n".join(lines)
    print(text)
    return text


def write_json(path: str, payload: object) -> None:
    Path(path).write_text(json.dumps(payload, indent=2))
