"""A reusable train / predict loop for the example detectors, and checkpoints.

* :func:`batch_order`: a deterministic data order (a seeded permutation per epoch, incomplete last
  batches dropped), so a run is reproducible from its seed.
* :func:`train_detector`: AdamW with a one-cycle learning rate (OpenPCDet's ``adam_onecycle``: 40 %
  warm-up, ``div_factor`` 10, momentum 0.95 -> 0.85 -> 0.95, weight decay 0.01), gradient-norm clipping at
  10 (OpenPCDet's ``GRAD_NORM_CLIP``) and a tqdm progress bar with the running loss.
* :func:`predict`: eval-mode detections per sample, in data order.
* :func:`save_checkpoint` / :func:`load_checkpoint`: weights plus a JSON-compatible configuration,
  loaded with ``weights_only=True``.

The loops take a ``make_batch(indices) -> RadarCameraBatch`` callable, so the same code serves the
synthetic scenes and KITTI-format datasets (and any data loader: pass ``batches`` of your own).

Call :func:`mssf_blocks.compat.spconv.enable_cpu_backward` before training a spconv detector on CPU.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError

try:
    from tqdm import tqdm
except ImportError:  # pragma: no cover - tqdm is in the examples extra
    class tqdm:  # type: ignore[no-redef]
        """Stand-in without a bar."""

        def __init__(self, it=None, **kw):
            self.it = it

        def __iter__(self):
            return iter(self.it)

        def update(self, n=1):
            pass

        def set_postfix(self, **kw):
            pass

        def close(self):
            pass

__all__ = ["batch_order", "train_detector", "predict", "save_checkpoint", "load_checkpoint", "CHECKPOINT_FORMAT"]

#: Value of the ``"format"`` entry of the checkpoints written here.
CHECKPOINT_FORMAT = "mssf-examples-detector/1"

PathLike = Union[str, Path]


def batch_order(num_samples: int, batch_size: int, steps: int, seed: int) -> List[List[int]]:
    """``steps`` batches of sample indices: a ``seed``-ed permutation per epoch, full batches only.

    Raises:
        MSSFError: when ``batch_size`` is not in ``[1, num_samples]`` or ``steps < 1``.
    """
    if not 1 <= batch_size <= num_samples:
        raise MSSFError(f"batch_size: expected 1 <= batch_size <= {num_samples} (the number of samples), "
                        f"got {batch_size}")
    if steps < 1:
        raise MSSFError(f"steps: expected a positive int, got {steps}")
    g = torch.Generator().manual_seed(int(seed))
    out: List[List[int]] = []
    while len(out) < steps:
        perm = torch.randperm(num_samples, generator=g).tolist()
        out += [perm[i:i + batch_size] for i in range(0, num_samples - batch_size + 1, batch_size)]
    return out[:steps]


def train_detector(
    model: nn.Module,
    batches: Iterable,
    steps: int,
    lr: float,
    weight_decay: float = 0.01,
    grad_clip: float = 10.0,
    desc: str = "train",
    log: Optional[Callable[[int, Dict[str, float]], None]] = None,
    progress: bool = True,
) -> Dict:
    """Train ``model`` for ``steps`` optimiser steps on ``batches`` (an iterable of batches).

    Args:
        model: a detector whose training-mode ``forward(batch)`` returns a dict with ``"loss"``.
        batches: yields at least ``steps`` :class:`~mssf_examples.data.RadarCameraBatch` es.
        steps: optimiser steps (the one-cycle schedule's length).
        lr: peak learning rate.
        weight_decay, grad_clip: AdamW weight decay and the gradient-norm clip.
        desc: progress-bar label.
        log: optional ``log(step, losses)`` called after every step.
        progress: show the tqdm bar.

    Returns:
        ``{"seconds", "seconds_per_step", "history": [losses per step]}``.
    """
    if steps < 1:
        raise MSSFError(f"steps: expected a positive int, got {steps}")
    if not lr > 0:
        raise MSSFError(f"lr: expected a positive learning rate, got {lr}")
    params = [p for p in model.parameters() if p.requires_grad]
    opt = torch.optim.AdamW(params, lr=lr, betas=(0.95, 0.99), weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.4, div_factor=10.0,
                                                base_momentum=0.85, max_momentum=0.95)
    model.train()
    history: List[Dict[str, float]] = []
    bar = tqdm(total=steps, desc=desc, unit="step", dynamic_ncols=True, disable=not progress)
    t0 = time.perf_counter()
    it = iter(batches)
    try:
        for step in range(steps):
            try:
                batch = next(it)
            except StopIteration:
                raise MSSFError(f"batches: expected at least {steps} batches, got {step}") from None
            losses = model(batch)
            opt.zero_grad(set_to_none=True)
            losses["loss"].backward()
            torch.nn.utils.clip_grad_norm_(params, grad_clip)
            opt.step()
            sched.step()
            row = {k: float(v.detach()) for k, v in losses.items()}
            history.append(row)
            if log is not None:
                log(step, row)
            bar.set_postfix(loss=f"{row['loss']:.3f}", lr=f"{sched.get_last_lr()[0]:.2e}")
            bar.update(1)
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    return dict(seconds=seconds, seconds_per_step=seconds / steps, history=history)


@torch.no_grad()
def predict(model: nn.Module, batches: Iterable, total: Optional[int] = None, desc: str = "predict",
            progress: bool = True) -> List[Dict[str, Tensor]]:
    """Eval-mode detections: one dict ``boxes (K, 7) float64, scores (K,), labels (K,)`` per sample.

    ``total`` (the number of batches) only sizes the progress bar.
    """
    model.eval()
    out: List[Dict[str, Tensor]] = []
    for batch in tqdm(batches, total=total, desc=desc, unit="batch", dynamic_ncols=True, disable=not progress):
        for p in model(batch):
            out.append({k: (v.double() if k == "boxes" else v).detach().cpu() for k, v in p.items()})
    return out


def save_checkpoint(path: PathLike, model: nn.Module, config: Dict) -> Path:
    """Save ``{"format", "model": state_dict, "config": config}`` (``config`` JSON-compatible)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": CHECKPOINT_FORMAT, "model": model.state_dict(), "config": config}, path)
    return path


def load_checkpoint(path: PathLike) -> Tuple[Dict[str, Tensor], Dict]:
    """Load a :func:`save_checkpoint` file: ``(state_dict, config)``.

    Raises:
        FileNotFoundError: the file does not exist.
        MSSFError: it is not a checkpoint written by :func:`save_checkpoint`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means "not our checkpoint"
        raise MSSFError(f"{path}: expected a checkpoint written by mssf_examples (train), "
                        f"could not load it: {exc}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != CHECKPOINT_FORMAT:
        got = ckpt.get("format") if isinstance(ckpt, dict) else type(ckpt).__name__
        raise MSSFError(f"{path}: expected a checkpoint with format {CHECKPOINT_FORMAT!r}, got {got!r}")
    return ckpt["model"], ckpt["config"]

