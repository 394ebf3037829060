"""Several processes, devices, mixed precision and resuming in the training CLI (``mssf_examples.training.distributed``).

On this CPU machine the multi-process runs use ``torchrun`` with the gloo backend on a tiny generated
VoD tree (:mod:`mssf_examples.scenes.synthetic` written by :func:`~mssf_examples.data.kitti_export.write_vod_tree`):

* two processes with micro-batches of 1 end with the same parameters as one process that accumulates
  the same two micro-batches per step (same global batch, same data order);
* a rank that fails (an unreadable frame only it reads) stops the whole run: non-zero exit, the rank
  and the cause named;
* every trainable parameter of every example detector gets a gradient in a training step (what
  ``DistributedDataParallel(find_unused_parameters=False)`` requires), MSDFF and SFF, n = 0, 1, 2.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.training import distributed  # noqa: E402
from mssf_examples.models.detectors import DETECTOR_NAMES, build_detector  # noqa: E402
from mssf_examples.data.kitti_export import write_vod_tree  # noqa: E402
from mssf_examples.models.presets import TINY  # noqa: E402
from mssf_examples.scenes.synthetic import SceneConfig, SyntheticDataset  # noqa: E402
from mssf_examples.training.loop import batch_order  # noqa: E402

REPO = Path(__file__).resolve().parents[3]

# One thread per process: tiny tensors (threads cost more than they save) and bit-reproducible spconv.
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    cfg = SceneConfig(image_size=(64, 104))
    root = tmp_path_factory.mktemp("vod")
    write_vod_tree(root, {"train": [SyntheticDataset("train", 4, cfg, seed=5)[i] for i in range(4)]})
    return root


def _args(root, out, *extra):
    return ["train", "--dataset", "vod", "--data-root", str(root), "--preset", "tiny", "--steps", "3", "--no-augment",
            "--batch-size", "2", "--threads", "1", "--no-progress", "--fusion-blocks", "1", "--out", str(out), *extra]


def _torchrun(nproc: int, argv, timeout: float = 300):
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(REPO / "src"), str(REPO / "examples"), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(nproc),
           "-m", "mssf_examples", *argv]
    return subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


def _parameters(out: Path):
    """The trained parameters (BatchNorm running statistics excluded: without --sync-bn each process keeps
    its own and DDP broadcasts rank 0's, so they are not expected to match a single process's)."""
    state = torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=True)["model"]
    return {k: v for k, v in state.items() if v.is_floating_point() and "running_" not in k}


# ---------------------------------------------------------------------------------------------------
# torchrun, gloo
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("detector,fusion", [("pointpillars", "msdff"), ("second", "sff")])
def test_two_processes_match_one_process_with_the_same_micro_batches(tree, tmp_path, detector, fusion):
    one, two = tmp_path / "one", tmp_path / "two"
    extra = ("--detector", detector, "--fusion", fusion)
    assert cli.main(_args(tree, one, "--accumulate", "2", *extra)) == 0
    r = _torchrun(2, _args(tree, two, *extra))
    assert r.returncode == 0, r.stderr[-3000:]
    cfg = json.loads((two / "config.json").read_text())
    assert cfg["processes"] == 2 and cfg["micro_batch"] == 1 and cfg["batch_size"] == 2
    assert json.loads((one / "config.json").read_text())["accumulate"] == 2
    a, b = _parameters(one), _parameters(two)
    assert a.keys() == b.keys() and len(a) > 50
    torch.manual_seed(0)  # the CLI's --seed
    init = build_detector(detector, cli.cli_tiny_preset(cli.DATASETS["vod"].preset, (64, 104)),
                          num_fusion_blocks=1, fusion=fusion).state_dict()
    moved = 0
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-6, msg=k)
        moved += int(not torch.equal(a[k], init[k]))
    assert moved > 0.5 * len(a)  # the runs did train (not two copies of the initial weights)
    # the logged losses are the mean over both processes' micro-batches, as over the accumulated ones
    la = json.loads((one / "train_log.json").read_text())
    lb = json.loads((two / "train_log.json").read_text())
    assert [r["loss"] for r in la] == pytest.approx([r["loss"] for r in lb], rel=1e-5)
    # rank 0 alone wrote: one progress summary line, no second config
    assert r.stderr.count("wrote ") == 1


def test_a_failing_rank_stops_the_run_with_a_clear_message(tree, tmp_path):
    """Rank 1's frame of step 2 is unreadable: rank 0 is then waiting in the gradient all-reduce; torchrun
    stops it and the run exits non-zero, naming rank 1 and the file."""
    import shutil

    bad = tmp_path / "vod"
    shutil.copytree(tree, bad)
    # which frame rank 1 reads in step 2 (global batch 1): the second half of it
    idx = batch_order(4, 2, 3, seed=0)[1][1]
    # its camera image, not its points: the CLI reads the first point files before training starts
    # (their layout), so a broken point file among them never reaches a training step
    frame = sorted((bad / "radar_5frames" / "training" / "image_2").iterdir())[idx]
    frame.write_bytes(b"xxxxx")  # not an image
    r = _torchrun(2, _args(bad, tmp_path / "out"), timeout=240)
    assert r.returncode != 0
    assert "rank 1 of 2 failed" in r.stderr and frame.name in r.stderr, r.stderr[-3000:]
    assert not (tmp_path / "out" / "checkpoint.pt").exists()


# ---------------------------------------------------------------------------------------------------
# the data split between processes and accumulation steps
# ---------------------------------------------------------------------------------------------------
def test_shard_batches_by_hand():
    g = [[10, 11, 12, 13], [20, 21, 22, 23]]
    # one process, 2 accumulation steps: halves in order
    assert distributed.shard_batches(g, 0, 1, 2) == [[10, 11], [12, 13], [20, 21], [22, 23]]
    # two processes: rank 0 the first half of every global batch, rank 1 the second
    assert distributed.shard_batches(g, 0, 2, 1) == [[10, 11], [20, 21]]
    assert distributed.shard_batches(g, 1, 2, 1) == [[12, 13], [22, 23]]
    # two processes x two steps: micro-step k of rank r reads quarter k * 2 + r
    assert distributed.shard_batches(g, 1, 2, 2) == [[11], [13], [21], [23]]
    with pytest.raises(MSSFError, match="--batch-size.*2 x 2 = 4.*got 2"):
        distributed.shard_batches([[1, 2]], 0, 2, 2)


def test_env_device_and_amp_resolution():
    assert distributed.distributed_from_env({}) == distributed.Distributed(0, 1, 0)
    d = distributed.distributed_from_env({"RANK": "3", "WORLD_SIZE": "4", "LOCAL_RANK": "1"})
    assert (d.rank, d.world_size, d.local_rank, d.is_main, d.enabled) == (3, 4, 1, False, True)
    with pytest.raises(MSSFError, match="RANK < WORLD_SIZE"):
        distributed.distributed_from_env({"RANK": "2", "WORLD_SIZE": "2"})
    assert distributed.resolve_device("cpu") == torch.device("cpu")
    assert distributed.resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(MSSFError, match="--device: expected auto, cpu, cuda or cuda:N, got 'gpu'"):
        distributed.resolve_device("gpu")
    if not torch.cuda.is_available():
        with pytest.raises(MSSFError, match="--device cuda:1: CUDA is not available"):
            distributed.resolve_device("cuda:1")
    cpu = torch.device("cpu")
    assert distributed.resolve_amp("off", cpu, "second") is None
    assert distributed.resolve_amp("bf16", cpu, "pointpillars") == torch.bfloat16
    with pytest.raises(MSSFError, match="--amp bf16: second uses spconv.*pointpillars"):
        distributed.resolve_amp("bf16", cpu, "second")


@pytest.mark.parametrize("extra,message", [
    (("--detector", "voxelnext", "--amp", "bf16"), "--amp bf16: voxelnext uses spconv"),
    (("--sync-bn", "--device", "cpu"), "--sync-bn: SyncBatchNorm runs on GPUs only"),
    (("--accumulate", "3"), "--batch-size: expected a multiple of processes x --accumulate = 1 x 3 = 3"),
    (("--device", "tpu"), "--device: expected auto, cpu, cuda or cuda:N, got 'tpu'"),
])
def test_runtime_options_that_cannot_work_are_clear_errors(tree, tmp_path, capsys, extra, message):
    with pytest.raises(SystemExit) as exc:
        cli.main(_args(tree, tmp_path, *extra))
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------------
# resuming, fp16 with a GradScaler (PointPillars runs under CPU autocast), checkpoints on the CPU
# ---------------------------------------------------------------------------------------------------
def test_resume_continues_the_run_exactly(tree, tmp_path, capsys):
    full, part, resumed = tmp_path / "full", tmp_path / "part", tmp_path / "resumed"
    four = ("--steps", "4", "--checkpoint-every", "2")
    assert cli.main(_args(tree, full, *four)) == 0
    assert cli.main(_args(tree, part, *four)) == 0
    step2 = part / "checkpoints" / "step_000002.pt"
    assert step2.is_file() and not (part / "checkpoints" / "step_000004.pt").exists()
    assert cli.main(_args(tree, resumed, *four, "--resume", str(step2))) == 0
    a, b = _parameters(full), _parameters(resumed)
    mid = {k: v for k, v in torch.load(step2, map_location="cpu", weights_only=True)["model"].items() if k in a}
    assert sum(not torch.equal(a[k], mid[k]) for k in a) > 0.5 * len(a)  # steps 3-4 changed the weights
    for k in a:
        torch.testing.assert_close(b[k], a[k], rtol=1e-5, atol=1e-7, msg=k)
    la = json.loads((full / "train_log.json").read_text())
    lb = json.loads((resumed / "train_log.json").read_text())
    assert len(lb) == 4 and lb[:2] == la[:2]
    assert [r["loss"] for r in lb[2:]] == pytest.approx([r["loss"] for r in la[2:]], rel=1e-5)
    # a resume with other options is refused, naming them
    with pytest.raises(SystemExit):
        cli.main(_args(tree, tmp_path / "x", "--steps", "5", "--resume", str(step2)))
    assert "steps (checkpoint 4, now 5)" in capsys.readouterr().err
    # the final checkpoint holds no training state
    with pytest.raises(SystemExit):
        cli.main(_args(tree, tmp_path / "y", *four, "--resume", str(full / "checkpoint.pt")))
    err = capsys.readouterr().err
    assert "--resume" in err and "training state" in err


def test_fp16_autocast_with_grad_scaler_on_the_cpu(tree, tmp_path):
    out = tmp_path / "fp16"
    assert cli.main(_args(tree, out, "--amp", "fp16", "--checkpoint-every", "1", "--device", "cpu")) == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["amp"] == "fp16" and cfg["device"] == "cpu"
    log = json.loads((out / "train_log.json").read_text())
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in log)
    ckpt = torch.load(out / "checkpoints" / "step_000001.pt", map_location="cpu", weights_only=True)
    assert ckpt["step"] == 1 and ckpt["train_state"]["scaler"]["scale"] > 0
    # every tensor of a checkpoint loads on the CPU (map_location), whatever device wrote it
    assert all(v.device.type == "cpu" for v in ckpt["model"].values())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="pinned memory needs CUDA")
def test_batches_pin_and_move_to_the_gpu():  # runs on GPU machines (benchmarks/gpu_check.py)
    sys.path.insert(0, str(Path(__file__).parents[1] / "models"))
    from test_detectors import make_batch

    batch = make_batch()
    pinned = batch.pin_memory()
    assert pinned.images.is_pinned() and all(p.is_pinned() for p in pinned.points)
    moved = pinned.to("cuda", non_blocking=True)
    assert moved.lidar2img.is_cuda and all(g.is_cuda for g in moved.gt_boxes)
    assert torch.equal(moved.images.cpu(), batch.images) and torch.equal(moved.points[1].cpu(), batch.points[1])


# ---------------------------------------------------------------------------------------------------
# no dead parameters (DistributedDataParallel with find_unused_parameters=False)
# ---------------------------------------------------------------------------------------------------
CONFIGS = [(0, "msdff"), (1, "msdff"), (2, "msdff"), (1, "sff"), (2, "sff")]


@pytest.mark.parametrize("n,fusion", CONFIGS, ids=[f"n{n}-{f}" for n, f in CONFIGS])
@pytest.mark.parametrize("name", DETECTOR_NAMES)
def test_every_parameter_gets_a_gradient(name, n, fusion):
    """One step: every trainable parameter has a gradient (none left out of the graph). MSDFF's query
    initialisation gets an exactly zero one in the very first step (the zero-initialised offsets and
    attention weights pass nothing back, as in Deformable DETR) and a non-zero one in the next. (An L1
    regression bias can also get an exact zero by sign cancellation; that is no dead parameter.)"""
    sys.path.insert(0, str(Path(__file__).parents[1] / "models"))
    from test_detectors import make_batch

    from mssf_examples.models.spconv_helpers import enable_cpu_backward

    enable_cpu_backward()
    batch = make_batch(seed=1)
    torch.manual_seed(0)
    model = build_detector(name, TINY, num_fusion_blocks=n, fusion=fusion).train()
    params = {k: p for k, p in model.named_parameters() if p.requires_grad}
    opt = torch.optim.SGD(params.values(), lr=1e-2)
    model(batch)["loss"].backward()
    assert [k for k, p in params.items() if p.grad is None] == []
    zero = [k for k, p in params.items() if ".query_init." in k]
    assert len(zero) == (4 if fusion == "msdff" and n else 0)
    opt.step()
    opt.zero_grad(set_to_none=True)
    model(batch)["loss"].backward()
    assert [k for k in zero if params[k].grad is None or not params[k].grad.abs().max() > 0] == []


def test_demo_takes_device_and_amp_and_refuses_what_cannot_run(capsys):
    sys.path.insert(0, str(REPO / "examples"))
    import train_demo

    args = train_demo.parse_args(["--quick", "--device", "cpu", "--amp", "bf16"])  # PointPillars: fine
    assert args.device == torch.device("cpu") and args.amp_dtype == torch.bfloat16
    with pytest.raises(SystemExit) as exc:
        train_demo.parse_args(["--quick", "--detector", "second", "--amp", "fp16", "--device", "cpu"])
    assert exc.value.code == 2 and "--amp fp16: second uses spconv" in capsys.readouterr().err
