"""``make gpu-check`` stage 4: the shipped mmdetection3d config trained through our entry on the device.

``python -m mssf_examples.mmdet3d train examples/configs/mmdet3d/mssf_pointpillars_vod.py --iters N
--image-checkpoint PATH`` on a generated View-of-Delft tree and a generated HTC-shaped image checkpoint (the
frozen branch must be loaded; ``mssf_examples.mmdet3d.generated``; batch size, workers, model and pipeline as
shipped), in a subprocess: N = 20 on a GPU, 2 with ``--smoke`` (CPU, images at 320 x 200). Reports mmengine's
time per iteration (the ``time:`` of its last training log line: the mean over the logged window), the last
loss, and the wall time of the whole run (start-up, data, validation included).

What it needs beside the library: mmdet3d 1.4 with mmcv's compiled ops, and on a GPU an mmcv built with CUDA
(``mmcv.ops.get_compiling_cuda_version()``); without them the stage reports why it did not run (it is no
failure of the check: a bare GPU machine has no mmcv with ops unless one is installed for its CUDA).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Dict

REPO = Path(__file__).resolve().parents[1]
CONFIG = REPO / "examples" / "configs" / "mmdet3d" / "mssf_pointpillars_vod.py"
_TRAIN_LINE = re.compile(r"Iter\(train\)\s*\[\s*(\d+)/(\d+)\].*?\btime: ([0-9.]+).*?\bloss: (\S+)")


def _not_run(device) -> str:
    """Why the stage cannot run on ``device`` here, or ''."""
    try:
        import mmcv._ext  # noqa: F401
        import mmdet3d  # noqa: F401
        from mmcv.ops import get_compiling_cuda_version
    except ImportError as exc:
        return f"not run: mmdet3d with mmcv's compiled ops does not import ({exc})"
    if device.type == "cuda" and get_compiling_cuda_version() in ("not available", "", None):
        return "not run: this mmcv's ops are built without CUDA (mmcv.ops.get_compiling_cuda_version())"
    return ""


def mmdet3d_training(device, smoke: bool, timeout_s: float) -> Dict[str, object]:
    """Train the shipped MSSF-PointPillars VoD config for 20 (smoke: 2) iterations on ``device``."""
    iters = 2 if smoke else 20
    row: Dict[str, object] = dict(config=str(CONFIG.relative_to(REPO)), iters=iters)
    reason = _not_run(device)
    if reason:
        row["skipped"] = reason
        return row
    from mssf_examples.mmdet3d.generated import write_generated_image_checkpoint, write_generated_vod

    with tempfile.TemporaryDirectory(prefix="mssf_gpu_check_mmdet3d_") as tmp:
        data_root = write_generated_vod(Path(tmp) / "vod")
        weights = write_generated_image_checkpoint(Path(tmp) / "htc_r50_fpn.pth")
        cmd = [sys.executable, "-m", "mssf_examples.mmdet3d", "train", str(CONFIG), "--data-root", str(data_root),
               "--iters", str(iters), "--work-dir", str(Path(tmp) / "work"), "--image-checkpoint", str(weights)]
        if smoke:
            cmd += ["--image-scale", "320", "200"]
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(REPO / "src"), str(REPO / "examples"), env.get("PYTHONPATH", "")])
        if device.type == "cuda" and device.index is not None:
            env["CUDA_VISIBLE_DEVICES"] = str(device.index)
        if device.type == "cpu":
            env["CUDA_VISIBLE_DEVICES"] = ""  # mmengine takes a visible GPU by itself
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            row["error"] = f"timed out after {timeout_s:.0f} s"
            return row
        row["wall_s"] = round(time.perf_counter() - t0, 1)
    log = r.stdout + r.stderr
    if r.returncode != 0:
        row["error"] = f"exit {r.returncode}: " + log[-1500:]
        return row
    lines = _TRAIN_LINE.findall(log)
    if not lines or int(lines[-1][0]) != iters:
        row["error"] = f"no training log line for iteration {iters}: " + log[-1500:]
        return row
    row["iter_s"] = float(lines[-1][2])
    row["loss"] = float(lines[-1][3])
    row["loss_finite"] = math.isfinite(row["loss"])
    return row
