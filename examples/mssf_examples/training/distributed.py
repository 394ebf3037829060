"""Devices, mixed precision and several processes (``torchrun`` / DistributedDataParallel) for training.

What the training CLI (``python -m mssf_examples train``) needs to run where users train:

* :func:`resolve_device`: ``auto | cpu | cuda | cuda:N`` -> a ``torch.device`` (under ``torchrun``,
  ``cuda`` means ``cuda:LOCAL_RANK``);
* :func:`resolve_amp`: ``off | bf16 | fp16`` -> the autocast dtype, refused where it cannot run
  (spconv's CPU kernels take neither bfloat16 nor float16: only PointPillars, pure torch, trains under
  CPU autocast);
* :class:`Distributed` / :func:`distributed_from_env` / :func:`init_distributed`: the process group of a
  ``torchrun`` launch (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``; NCCL on CUDA, gloo on the CPU);
* :func:`shard_batches`: the share of every *global* batch one process reads, so that ``W`` processes
  with ``K`` accumulation steps see exactly the micro-batches a single process with ``W * K``
  accumulation steps sees (same data order, same optimiser steps, same learning-rate schedule);
* :func:`wrap_model`: ``DistributedDataParallel`` with ``find_unused_parameters=False`` (every example
  detector gives every trainable parameter a gradient in every step; ``tests/examples/training/test_distributed.py``
  checks it), optionally after ``SyncBatchNorm`` conversion (CUDA only: PyTorch has no CPU version).

See ``docs/gpus.md`` for the commands (one GPU, several GPUs, several nodes, mixed precision).
"""

from __future__ import annotations

import contextlib
import datetime
import os
from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import torch
from torch import Tensor, nn

from mssf_blocks.torch_versions import require
from mssf_blocks.errors import MSSFError

__all__ = [
    "AMP_MODES",
    "Distributed",
    "Runtime",
    "distributed_from_env",
    "init_distributed",
    "resolve_device",
    "resolve_amp",
    "autocast",
    "shard_batches",
    "wrap_model",
    "unwrap_model",
    "mean_over_processes",
    "report_failure",
    "shutdown",
    "add_arguments",
]

#: ``--amp`` choices and the autocast dtype of each.
AMP_MODES: Dict[str, Optional[torch.dtype]] = {"off": None, "bf16": torch.bfloat16, "fp16": torch.float16}

#: Detectors without spconv (they can run under CPU autocast).
_PURE_TORCH_DETECTORS = ("pointpillars",)


@dataclass(frozen=True)
class Distributed:
    """Where this process sits in a ``torchrun`` launch (``world_size == 1``: a plain single process)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """Rank 0: the process that logs, shows progress, writes checkpoints and evaluates."""
        return self.rank == 0


def _env_int(env, name: str, default: int) -> int:
    text = env.get(name)
    if text is None or text == "":
        return default
    try:
        return int(text)
    except ValueError:
        raise MSSFError(f"${name}: expected an int (set by torchrun), got {text!r}") from None


def distributed_from_env(env=None) -> Distributed:
    """The rank, world size and local rank ``torchrun`` exports (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``).

    Without them: one process, rank 0.

    Raises:
        MSSFError: inconsistent values (e.g. ``RANK >= WORLD_SIZE``).
    """
    env = os.environ if env is None else env
    world = _env_int(env, "WORLD_SIZE", 1)
    rank = _env_int(env, "RANK", 0)
    local = _env_int(env, "LOCAL_RANK", rank)
    if world < 1 or not 0 <= rank < world or local < 0:
        raise MSSFError(f"$RANK / $WORLD_SIZE / $LOCAL_RANK: expected 0 <= RANK < WORLD_SIZE and LOCAL_RANK >= 0, "
                        f"got {rank} / {world} / {local}")
    return Distributed(rank, world, local)


def resolve_device(spec: str, dist: Distributed = Distributed()) -> torch.device:
    """``"auto" | "cpu" | "cuda" | "cuda:N"`` -> the device this process trains on.

    ``auto`` is CUDA when ``torch.cuda.is_available()``, else the CPU. Under ``torchrun`` (``world_size
    > 1``) ``cuda`` / ``auto`` mean ``cuda:LOCAL_RANK``, one GPU per process; ``cuda:N`` is refused
    there (select GPUs with ``CUDA_VISIBLE_DEVICES``).

    Raises:
        MSSFError: an unknown spec, CUDA asked for but not available, ``N`` out of range.
    """
    text = str(spec).strip().lower()
    if text == "auto":
        text = "cuda" if torch.cuda.is_available() else "cpu"
    if text == "cpu":
        return torch.device("cpu")
    if text != "cuda" and not (text.startswith("cuda:") and text[5:].isdigit()):
        raise MSSFError(f"--device: expected auto, cpu, cuda or cuda:N, got {spec!r}")
    if not torch.cuda.is_available():
        raise MSSFError(f"--device {spec}: CUDA is not available here (torch {torch.__version__}, "
                        f"torch.cuda.is_available() is False); use --device cpu")
    count = torch.cuda.device_count()
    if text == "cuda":
        index = dist.local_rank if dist.enabled else torch.cuda.current_device()
    else:
        if dist.enabled:
            raise MSSFError(f"--device {spec}: under torchrun every process takes cuda:LOCAL_RANK; pass --device "
                            f"cuda (or auto) and choose the GPUs with CUDA_VISIBLE_DEVICES")
        index = int(text[5:])
    if index >= count:
        raise MSSFError(f"--device {spec}: expected a GPU index < {count} (the visible GPUs), got {index}"
                        + (" (LOCAL_RANK; more processes per node than GPUs?)" if dist.enabled else ""))
    return torch.device("cuda", index)


def resolve_amp(mode: str, device: torch.device, detector: str) -> Optional[torch.dtype]:
    """The autocast dtype of ``--amp mode`` on ``device`` for ``detector`` (``None``: full float32).

    The fusion blocks keep projection and sampling in float32 under autocast either way. On the CPU
    the spconv detectors (SECOND, CenterPoint, VoxelNeXt) cannot run under autocast: spconv's CPU
    kernels take neither bfloat16 nor float16. float16 on CUDA needs a ``GradScaler`` (the training
    loop makes one).

    Raises:
        MSSFError: an unknown mode, or a combination that cannot run (saying what can).
    """
    if mode not in AMP_MODES:
        raise MSSFError(f"--amp: expected one of {tuple(AMP_MODES)}, got {mode!r}")
    dtype = AMP_MODES[mode]
    if dtype is None:
        return None
    if device.type == "cpu" and detector not in _PURE_TORCH_DETECTORS:
        raise MSSFError(f"--amp {mode}: {detector} uses spconv, whose CPU kernels take no {dtype} (only "
                        f"{', '.join(_PURE_TORCH_DETECTORS)} trains under CPU autocast); use --amp off on the CPU "
                        f"or --device cuda")
    if device.type == "cpu" and dtype == torch.float16:
        require("cpu_float16_autocast", f"--amp {mode}")  # (torch-version dependent: mssf_blocks.torch_versions)
    if device.type == "cuda" and dtype == torch.bfloat16 and not torch.cuda.is_bf16_supported():
        raise MSSFError(f"--amp bf16: {torch.cuda.get_device_name(device)} has no bfloat16 support; use --amp fp16")
    return dtype


def autocast(device: torch.device, dtype: Optional[torch.dtype]):
    """``torch.autocast(device.type, dtype)``, or a no-op context for ``dtype=None``."""
    if dtype is None:
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=dtype)


def init_distributed(dist: Distributed, device: torch.device, timeout_s: float = 1800.0) -> None:
    """Join the ``torchrun`` process group: NCCL for CUDA devices, gloo for the CPU (no-op for one process).

    ``torchrun`` sets ``MASTER_ADDR`` / ``MASTER_PORT`` (from ``--rdzv-endpoint`` or ``--standalone``).
    """
    if not dist.enabled or torch.distributed.is_initialized():
        return
    if not torch.distributed.is_available():
        raise MSSFError("torch.distributed is not available in this torch build; run one process")
    if device.type == "cuda":
        torch.cuda.set_device(device)
    backend = "nccl" if device.type == "cuda" else "gloo"
    kwargs = dict(device_id=device) if device.type == "cuda" else {}
    torch.distributed.init_process_group(backend, rank=dist.rank, world_size=dist.world_size,
                                         timeout=datetime.timedelta(seconds=timeout_s), **kwargs)


def shard_batches(global_batches: Sequence[Sequence[int]], rank: int, world_size: int,
                  accumulate: int) -> List[List[int]]:
    """The micro-batches process ``rank`` reads: ``accumulate`` per global batch, in order.

    Global batch ``g`` (``B`` sample indices) is cut into ``world_size * accumulate`` consecutive
    micro-batches of ``m = B / (world_size * accumulate)``; micro-step ``k`` of process ``r`` reads
    ``g[(k * world_size + r) * m : ... + m]``. So every optimiser step averages the gradients of the
    same ``W * K`` micro-batches whatever the split between processes and accumulation steps, and one
    process with ``K = W`` reproduces a ``W``-process run (the DDP equivalence test relies on it).

    Raises:
        MSSFError: ``B`` not divisible by ``world_size * accumulate``, bad ``rank``.
    """
    if world_size < 1 or not 0 <= rank < world_size:
        raise MSSFError(f"rank: expected 0 <= rank < world_size={world_size}, got {rank}")
    if accumulate < 1:
        raise MSSFError(f"accumulate: expected a positive int, got {accumulate}")
    parts = world_size * accumulate
    out: List[List[int]] = []
    for g in global_batches:
        g = list(g)
        if len(g) % parts:
            raise MSSFError(f"--batch-size: expected a multiple of processes x --accumulate = {world_size} x "
                            f"{accumulate} = {parts} (the global batch is split evenly), got {len(g)}")
        m = len(g) // parts
        for k in range(accumulate):
            start = (k * world_size + rank) * m
            out.append(g[start:start + m])
    return out


def wrap_model(model: nn.Module, device: torch.device, dist: Distributed, sync_bn: bool = False) -> nn.Module:
    """``model`` on ``device``; under ``torchrun`` wrapped in ``DistributedDataParallel``.

    ``find_unused_parameters=False``: the example detectors use every trainable parameter in every
    training step (checked over all of them, MSDFF and SFF, n = 0, 1, 2), so DDP needs no extra
    graph traversal. ``sync_bn`` converts every BatchNorm (also the fusion blocks' ``BatchNorm1d``)
    to ``SyncBatchNorm``, whose statistics then span the global batch; PyTorch implements it for
    GPUs only.

    Raises:
        MSSFError: ``sync_bn`` on the CPU.
    """
    if sync_bn and device.type == "cpu":
        raise MSSFError("--sync-bn: SyncBatchNorm runs on GPUs only (PyTorch has no CPU implementation); "
                        "drop --sync-bn or use --device cuda")
    if sync_bn and dist.enabled:
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
    model = model.to(device)
    if not dist.enabled:
        return model
    ids = [device.index] if device.type == "cuda" else None
    return nn.parallel.DistributedDataParallel(model, device_ids=ids, find_unused_parameters=False)


def unwrap_model(model: nn.Module) -> nn.Module:
    """The detector inside a ``DistributedDataParallel`` wrapper (itself otherwise)."""
    return model.module if isinstance(model, nn.parallel.DistributedDataParallel) else model


def mean_over_processes(values: Tensor) -> Tensor:
    """``values`` averaged over the processes of the group (itself without one): for logged losses."""
    if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
        return values
    values = values.clone()
    torch.distributed.all_reduce(values)
    return values / torch.distributed.get_world_size()



@dataclass(frozen=True)
class Runtime:
    """Where and how one training process runs: its place in the launch, device, autocast dtype."""

    dist: Distributed
    device: torch.device
    amp: str
    amp_dtype: Optional[torch.dtype]
    accumulate: int
    sync_bn: bool
    micro_batch: int

    @classmethod
    def from_args(cls, args, batch_size: int, env=None) -> "Runtime":
        """From the CLI's ``--device --amp --accumulate --sync-bn`` and the global ``batch_size``.

        Raises:
            MSSFError: naming the option that cannot work here and why.
        """
        dist = distributed_from_env(env)
        device = resolve_device(args.device, dist)
        dtype = resolve_amp(args.amp, device, args.detector)
        if args.sync_bn and device.type == "cpu":
            raise MSSFError("--sync-bn: SyncBatchNorm runs on GPUs only (PyTorch has no CPU implementation); "
                            "drop --sync-bn or use --device cuda")
        parts = dist.world_size * args.accumulate
        if batch_size % parts:
            raise MSSFError(f"--batch-size: expected a multiple of processes x --accumulate = {dist.world_size} x "
                            f"{args.accumulate} = {parts} (it is the global batch, split evenly), got {batch_size}")
        return cls(dist, device, args.amp, dtype, args.accumulate, bool(args.sync_bn), batch_size // parts)

    @property
    def config(self) -> Dict:
        """What the run's ``config.json`` records about it."""
        return dict(device=str(self.device), amp=self.amp, processes=self.dist.world_size,
                    accumulate=self.accumulate, micro_batch=self.micro_batch, sync_bn=self.sync_bn)

    def describe(self) -> str:
        parts = [f"{self.device}", f"amp {self.amp}"]
        if self.dist.enabled:
            parts.append(f"{self.dist.world_size} processes")
        if self.accumulate > 1:
            parts.append(f"{self.accumulate} accumulation steps")
        if self.dist.enabled or self.accumulate > 1:
            parts.append(f"micro-batches of {self.micro_batch}")
        return ", ".join(parts)



def report_failure(exc: BaseException, env=None) -> None:
    """Under ``torchrun``: print which rank failed and why (one line on stderr, before the traceback).

    ``torchrun`` then stops the other processes (they would wait for this one in the next
    all-reduce) and exits non-zero with a summary naming the first failed rank.
    """
    import sys

    try:
        dist = distributed_from_env(env)
    except MSSFError:
        return
    if dist.enabled:
        print(f"mssf_examples: rank {dist.rank} of {dist.world_size} failed: {type(exc).__name__}: {exc}",
              file=sys.stderr, flush=True)


def shutdown(success: bool = True) -> None:
    """Leave the process group (if this process joined one).

    After a successful run every rank first waits for the others (a barrier): rank 0 still writes its
    checkpoint when the others are done, and a rank that tore its gloo connections down and exited
    meanwhile crashed now and then at interpreter exit ("terminate called without an active
    exception", SIGSEGV; seen once in 16 two-process runs of tests/examples/training/test_distributed.py).
    After a failure there is no barrier (the failed rank would never reach it; torchrun stops the
    others)."""
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        if success:
            torch.distributed.barrier()
        torch.distributed.destroy_process_group()


def add_arguments(p, training: bool) -> None:
    """The ``--device`` option (train and eval) and, with ``training``, ``--amp``, ``--accumulate``,
    ``--sync-bn``, ``--checkpoint-every`` and ``--resume`` of ``python -m mssf_examples``."""
    from pathlib import Path

    p.add_argument("--device", default="auto", metavar="{auto,cpu,cuda,cuda:N}",
                   help="where to run (default auto: CUDA when available; under torchrun cuda:LOCAL_RANK)")
    if not training:
        return
    p.add_argument("--amp", choices=tuple(AMP_MODES), default="off",
                   help="mixed precision: bf16 or fp16 autocast (fp16 with a GradScaler); the fusion blocks keep "
                        "projection and sampling in float32. On the CPU only pointpillars (spconv takes no bf16)")
    p.add_argument("--accumulate", type=_positive_int, default=1,
                   help="micro-batches per optimiser step; --batch-size (the global batch, the schedule's unit) "
                        "must be a multiple of processes x accumulate")
    p.add_argument("--sync-bn", action="store_true",
                   help="under torchrun: SyncBatchNorm, statistics over the global batch (GPUs only)")
    p.add_argument("--checkpoint-every", type=_non_negative_int, default=0,
                   help="also write <out>/checkpoints/step_<N>.pt every N steps, resumable (default 0: never)")
    p.add_argument("--resume", type=Path, default=None,
                   help="continue the run of this checkpoints/step_<N>.pt (same data, model and schedule options; "
                        "device, processes and --accumulate may differ)")


def _positive_int(text: str) -> int:
    return _int_at_least(text, 1, "a positive int")


def _non_negative_int(text: str) -> int:
    return _int_at_least(text, 0, "an int >= 0")


def _int_at_least(text: str, low: int, what: str) -> int:
    import argparse

    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if v < low:
        raise argparse.ArgumentTypeError(f"expected {what}, got {v}")
    return v
