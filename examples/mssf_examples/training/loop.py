"""A reusable train / predict loop for the example detectors, and checkpoints.

* :func:`batch_order`: a deterministic data order (a seeded permutation per epoch, incomplete last
  batches dropped), so a run is reproducible from its seed.
* :func:`train_detector`: AdamW with a one-cycle learning rate (OpenPCDet's ``adam_onecycle``: 40 %
  warm-up, ``div_factor`` 10, momentum 0.95 -> 0.85 -> 0.95, weight decay 0.01), gradient-norm clipping at
  10 (OpenPCDet's ``GRAD_NORM_CLIP``) and a tqdm progress bar with the running loss.
  It runs on the model's device, optionally under autocast (``amp_dtype``; float16 with a
  ``GradScaler``), with gradient accumulation, inside ``DistributedDataParallel`` (one all-reduce per
  optimiser step) and resumes from a checkpoint's ``train_state``.
* :func:`predict`: eval-mode detections per sample, in data order (moved back to the CPU).
* :func:`save_checkpoint` / :func:`load_checkpoint`: weights plus a JSON-compatible configuration
  (and, for resuming, the optimiser / schedule / scaler state and the step), loaded with
  ``weights_only=True`` onto the CPU, so a checkpoint written on a GPU loads anywhere;
  :func:`load_resume_state` reads all of it back.

The loops take a ``make_batch(indices) -> RadarCameraBatch`` callable, so the same code serves the
synthetic scenes and KITTI-format datasets (and any data loader: pass ``batches`` of your own).

Call :func:`mssf_blocks.integrations.spconv.enable_cpu_backward` before training a spconv detector on CPU.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Tuple, Union

import torch
from torch import Tensor, nn

from mssf_blocks.torch_versions import grad_scaler
from mssf_blocks.errors import MSSFError

from .distributed import autocast, mean_over_processes, unwrap_model

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

__all__ = ["batch_order", "train_detector", "predict", "save_checkpoint", "load_checkpoint", "load_resume_state",
           "CHECKPOINT_FORMAT", "RESUME_KEYS"]

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
    device: Optional[torch.device] = None,
    amp_dtype: Optional[torch.dtype] = None,
    accumulate: int = 1,
    start_step: int = 0,
    state: Optional[Dict] = None,
    checkpoint: Optional[Callable[[int, Dict], None]] = None,
    checkpoint_every: int = 0,
) -> Dict:
    """Train ``model`` for ``steps`` optimiser steps on ``batches`` (an iterable of batches).

    Args:
        model: a detector whose training-mode ``forward(batch)`` returns a dict with ``"loss"``, on
            ``device``; may be wrapped in ``DistributedDataParallel`` (then ``batches`` are this
            process's share, :func:`mssf_examples.training.distributed.shard_batches`).
        batches: yields ``accumulate`` micro-batches (:class:`~mssf_examples.data.batch.RadarCameraBatch`)
            per remaining optimiser step, i.e. ``(steps - start_step) * accumulate`` in all.
        steps: optimiser steps (the one-cycle schedule's length; one step = one global batch).
        lr: peak learning rate.
        weight_decay, grad_clip: AdamW weight decay and the gradient-norm clip.
        desc: progress-bar label.
        log: optional ``log(step, losses)`` called after every step.
        progress: show the tqdm bar (pass ``False`` on every rank but 0).
        device: where batches are moved (``batch.to(device, non_blocking=True)``); default: the
            device of the model's first parameter.
        amp_dtype: ``None`` (float32), ``torch.bfloat16`` or ``torch.float16`` autocast; float16
            uses a ``GradScaler`` (its scale is part of ``state``).
        accumulate: micro-batches per optimiser step; their gradients are averaged (under DDP the
            gradient all-reduce runs once per step, on the last micro-batch).
        start_step, state: resume: the steps already done and the ``train_state`` of a checkpoint
            (``{"optimizer", "scheduler", "scaler"}`` state dicts and the ``"history"`` so far) to
            continue from.
        checkpoint, checkpoint_every: ``checkpoint(step, train_state)`` after every
            ``checkpoint_every``-th step (``0``: never); ``step`` counts the steps done.

    Returns:
        ``{"seconds", "seconds_per_step", "history": [losses per step, averaged over the micro-batches
        and processes; from step 0 when resumed], "train_state"}``.
    """
    if steps < 1:
        raise MSSFError(f"steps: expected a positive int, got {steps}")
    if not lr > 0:
        raise MSSFError(f"lr: expected a positive learning rate, got {lr}")
    if accumulate < 1:
        raise MSSFError(f"accumulate: expected a positive int, got {accumulate}")
    if not 0 <= start_step < steps:
        raise MSSFError(f"start_step: expected 0 <= start_step < steps={steps}, got {start_step}")
    params = [p for p in model.parameters() if p.requires_grad]
    if device is None:
        device = params[0].device if params else torch.device("cpu")
    opt = torch.optim.AdamW(params, lr=lr, betas=(0.95, 0.99), weight_decay=weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps, pct_start=0.4, div_factor=10.0,
                                                base_momentum=0.85, max_momentum=0.95)
    scaler = grad_scaler(device.type, enabled=amp_dtype == torch.float16)  # (mssf_blocks.torch_versions)
    if state is not None:
        opt.load_state_dict(state["optimizer"])  # moves the moments onto the parameters' device
        sched.load_state_dict(state["scheduler"])
        if state.get("scaler") is not None:
            scaler.load_state_dict(state["scaler"])
    no_sync = getattr(model, "no_sync", None)  # DistributedDataParallel: all-reduce once per step
    model.train()
    history: List[Dict[str, float]] = list(state.get("history", [])) if state is not None else []
    bar = tqdm(total=steps, initial=start_step, desc=desc, unit="step", dynamic_ncols=True, disable=not progress)
    t0 = time.perf_counter()
    it = iter(batches)

    def train_state() -> Dict:
        return dict(optimizer=opt.state_dict(), scheduler=sched.state_dict(),
                    scaler=scaler.state_dict() if scaler.is_enabled() else None, history=list(history))

    try:
        for step in range(start_step, steps):
            opt.zero_grad(set_to_none=True)
            sums: Dict[str, Tensor] = {}
            for k in range(accumulate):
                try:
                    batch = next(it)
                except StopIteration:
                    raise MSSFError(f"batches: expected {(steps - start_step) * accumulate} micro-batches, got "
                                    f"{(step - start_step) * accumulate + k}") from None
                if device.type != "cpu" and hasattr(batch, "to"):  # pinned by the loader: asynchronous copy
                    batch = batch.to(device, non_blocking=True)
                sync = no_sync is None or k == accumulate - 1
                with contextlib.nullcontext() if sync else no_sync():
                    with autocast(device, amp_dtype):
                        losses = model(batch)
                    scaler.scale(losses["loss"].float() / accumulate).backward()
                for name, v in losses.items():
                    sums[name] = sums.get(name, 0) + v.detach().float() / accumulate
            scaler.unscale_(opt)
            torch.nn.utils.clip_grad_norm_(params, grad_clip)
            lr_used = sched.get_last_lr()[0]  # (the rate this step used; sched.step() sets the next one)
            scaler.step(opt)
            scaler.update()
            sched.step()
            # one host sync per step (the logged losses), averaged over the processes
            names = list(sums)
            means = mean_over_processes(torch.stack([sums[n] for n in names])).tolist()
            row = dict(zip(names, means))
            history.append(row)
            if log is not None:
                log(step, row)
            if checkpoint is not None and checkpoint_every and (step + 1) % checkpoint_every == 0 and step + 1 < steps:
                checkpoint(step + 1, train_state())
            bar.set_postfix(loss=f"{row['loss']:.3f}", lr=f"{lr_used:.2e}")
            bar.update(1)
    finally:
        bar.close()
    seconds = time.perf_counter() - t0
    done = steps - start_step
    return dict(seconds=seconds, seconds_per_step=seconds / done, history=history, train_state=train_state())


@torch.no_grad()
def predict(model: nn.Module, batches: Iterable, total: Optional[int] = None, desc: str = "predict",
            progress: bool = True) -> List[Dict[str, Tensor]]:
    """Eval-mode detections: one dict ``boxes (K, 7) float64, scores (K,), labels (K,)`` per sample.

    ``total`` (the number of batches) only sizes the progress bar.
    """
    model.eval()
    first = next(iter(model.parameters()), None)
    device = first.device if first is not None else torch.device("cpu")
    out: List[Dict[str, Tensor]] = []
    for batch in tqdm(batches, total=total, desc=desc, unit="batch", dynamic_ncols=True, disable=not progress):
        if device.type != "cpu" and hasattr(batch, "to"):
            batch = batch.to(device, non_blocking=True)
        for p in model(batch):
            out.append({k: (v.double() if k == "boxes" else v).detach().cpu() for k, v in p.items()})
    return out


def save_checkpoint(path: PathLike, model: nn.Module, config: Dict, train_state: Optional[Dict] = None,
                    step: Optional[int] = None) -> Path:
    """Save ``{"format", "model": state_dict, "config": config}`` (``config`` JSON-compatible).

    With ``train_state`` (:func:`train_detector`'s) and ``step`` (optimiser steps done) the file can
    resume the run (:func:`load_resume_state`). A ``DistributedDataParallel`` model is saved unwrapped.
    Written to a hidden temporary file (``.<name>.tmp``: a partial one never sorts after, or globs as,
    the real checkpoints), flushed to the disk (``fsync``) and renamed, then the folder is synced: a
    reader never sees half a checkpoint, also after a power loss.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ckpt = {"format": CHECKPOINT_FORMAT, "model": unwrap_model(model).state_dict(), "config": config}
    if train_state is not None:
        ckpt.update(train_state=train_state, step=int(step))
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        torch.save(ckpt, f)
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(path)
    _fsync_dir(path.parent)
    return path


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (POSIX; a no-op where folders cannot be opened)."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:  # pragma: no cover - e.g. Windows
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover - some file systems refuse fsync on a folder
        pass
    finally:
        os.close(fd)


def _load(path: PathLike) -> Dict:
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
    return ckpt


#: Configuration entries a resumed run must share with the run it continues (the model, the data and
#: the schedule; the device, the number of processes and the accumulation steps may differ).
RESUME_KEYS = ("dataset", "split", "detector", "fusion_blocks", "fusion", "preset_name", "image_scale",
               "train_image_branch", "steps", "batch_size", "lr", "seed", "preset")


def load_resume_state(path: PathLike, expect_config: Optional[Dict] = None) -> Dict:
    """A resumable checkpoint: ``{"model", "config", "train_state", "step"}``, tensors on the CPU.

    With ``expect_config`` (the new run's configuration) its :data:`RESUME_KEYS` entries must equal
    the checkpoint's.

    Raises:
        FileNotFoundError: the file does not exist.
        MSSFError: not a :func:`save_checkpoint` file, one without a training state (a final
            checkpoint of a finished run), or options that differ (naming them).
    """
    ckpt = _load(path)
    if "train_state" not in ckpt:
        raise MSSFError(f"{path}: expected a checkpoint with a training state (written every --checkpoint-every "
                        f"steps, under <out>/checkpoints/), got a final checkpoint without one")
    if expect_config is not None:
        old = ckpt["config"]
        differ = [k for k in RESUME_KEYS if old.get(k) != expect_config.get(k)]
        if differ:
            named = [f"{k} (checkpoint {old.get(k)!r}, now {expect_config.get(k)!r})" for k in differ if k != "preset"]
            raise MSSFError(f"{path}: expected the options of the run it continues; these differ: "
                            + (", ".join(named) if named else "the preset"))
    return ckpt


def load_checkpoint(path: PathLike) -> Tuple[Dict[str, Tensor], Dict]:
    """Load a :func:`save_checkpoint` file: ``(state_dict, config)``.

    Raises:
        FileNotFoundError: the file does not exist.
        MSSFError: it is not a checkpoint written by :func:`save_checkpoint`.
    """
    ckpt = _load(path)
    return ckpt["model"], ckpt["config"]
