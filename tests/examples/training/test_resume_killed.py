"""Issue 33, item 6: a training run killed (SIGKILL) and resumed ends bit-exact with an uninterrupted run,
with augmentation on; a partial checkpoint ``.tmp`` never sorts or globs as a real checkpoint; the progress
bar shows the learning rate the step used."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

pytest.importorskip("spconv")
pytest.importorskip("PIL")

from mssf_examples.cli import commands as cli  # noqa: E402
from mssf_examples.training import loop as training  # noqa: E402

sys.path.insert(0, str(Path(__file__).parents[1] / "helpers"))
from generated_tree import write_generated_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
STEPS = 4


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    return write_generated_tree(tmp_path_factory.mktemp("vod"))[0]


def _args(root, out, *extra):  # augmentation: the recipe's (on)
    return ["train", "--dataset", "vod", "--data-root", str(root), "--preset", "tiny", "--steps", str(STEPS),
            "--batch-size", "2", "--threads", "1", "--no-progress", "--checkpoint-every", "1",
            "--fusion-blocks", "1", "--out", str(out), *extra]


def _weights(out):
    return torch.load(out / "checkpoint.pt", map_location="cpu", weights_only=True)["model"]


def _killed_at(root, out, step: int, timeout: float = 240.0) -> None:
    """Run the CLI in a child and SIGKILL it as soon as checkpoint ``step`` exists."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "mssf_examples", *_args(root, out)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    target = out / "checkpoints" / f"step_{step:06d}.pt"
    t0 = time.monotonic()
    try:
        while not target.exists() and proc.poll() is None and time.monotonic() - t0 < timeout:
            time.sleep(0.01)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert target.exists(), f"the child wrote no {target.name}"


def test_killed_runs_resume_bit_exact_with_augmentation(tree, tmp_path):
    full = tmp_path / "full"
    assert cli.main(_args(tree, full)) == 0
    want = _weights(full)
    first = torch.load(full / "checkpoints" / "step_000001.pt", map_location="cpu", weights_only=True)
    assert first["train_state"]["rng_states"][0]["augment"] is not None  # augmentation on: its state is kept
    for kill in (1, 3):
        part = tmp_path / f"killed_{kill}"
        _killed_at(tree, part, kill)
        # a checkpoint half written when the power went: hidden, it sorts first and is no step_*.pt
        (part / "checkpoints" / ".step_000009.pt.tmp").write_bytes(b"PK\x03\x04 half")
        real = sorted((part / "checkpoints").glob("step_*.pt"))
        assert sorted(os.listdir(part / "checkpoints"))[0].endswith(".tmp")
        resumed = tmp_path / f"resumed_{kill}"
        assert cli.main(_args(tree, resumed, "--resume", str(real[-1]))) == 0
        got = _weights(resumed)
        assert got.keys() == want.keys()
        differ = [k for k in want if not torch.equal(got[k], want[k])]
        assert not differ, f"killed at step {kill}, resumed from {real[-1].name}: {len(differ)} tensors differ"


def test_save_checkpoint_hidden_tmp_fsynced_before_rename(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, Path.replace
    monkeypatch.setattr(training.os, "fsync", lambda fd: (events.append("fsync"), real_fsync(fd)))

    def replace(self, target):
        events.append(("rename", self.name, sorted([self.name, Path(target).name, "step_000000.pt"])))
        return real_replace(self, target)

    monkeypatch.setattr(Path, "replace", replace)
    path = training.save_checkpoint(tmp_path / "c" / "step_000001.pt", torch.nn.Linear(2, 2), {"a": 1})
    assert sorted(p.name for p in path.parent.iterdir()) == ["step_000001.pt"]
    renames = [e for e in events if e != "fsync"]
    assert len(renames) == 1
    _, tmp_name, order = renames[0]
    # the partial file sorts before every real checkpoint and is no step_*.pt
    assert order[0] == tmp_name and not Path(tmp_name).match("step_*.pt")
    assert events.index(renames[0]) > events.index("fsync")  # flushed to the disk before the rename
    assert events[-1] == "fsync"  # then the folder


class _Bar:
    posts = []

    def __init__(self, *a, **k):
        pass

    def set_postfix(self, **kw):
        _Bar.posts.append(kw)

    def update(self, n=1):
        pass

    def close(self):
        pass


def test_progress_bar_shows_the_lr_the_step_used(monkeypatch):
    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.ones(2))

        def forward(self, batch):
            return {"loss": (self.w * batch).sum()}

    _Bar.posts = []
    monkeypatch.setattr(training, "tqdm", _Bar)
    model = Model()
    seen = []  # what the optimiser held while each step ran (the reference)

    def hook(opt, args, kwargs):
        seen.append(opt.param_groups[0]["lr"])

    from torch.optim.optimizer import register_optimizer_step_pre_hook

    handle = register_optimizer_step_pre_hook(hook)
    try:
        training.train_detector(model, [torch.ones(2)] * 5, 5, 1e-2, progress=True)
    finally:
        handle.remove()
    assert len(seen) == 5 and len(set(seen)) == 5  # one-cycle: a new rate every step
    assert [p["lr"] for p in _Bar.posts] == [f"{v:.2e}" for v in seen]


def _fake_states(tag: int):
    return [torch.tensor([tag, 1], dtype=torch.uint8), torch.tensor([tag, 2], dtype=torch.uint8)]


def test_cuda_random_states_saved_only_where_cuda_runs(monkeypatch):
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: _fake_states(5))
    for available, initialised, want in ((True, True, _fake_states(5)), (True, False, None), (False, False, None)):
        monkeypatch.setattr(torch.cuda, "is_available", lambda a=available: a)
        monkeypatch.setattr(torch.cuda, "is_initialized", lambda i=initialised: i)
        got = cli._cuda_rng()  # a CPU run on a GPU machine (not initialised) must not start CUDA
        assert (got is None) if want is None else all(torch.equal(g, w) for g, w in zip(got, want))


def test_cuda_random_states_restored_on_resume(tree, tmp_path, monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(cli, "_cuda_rng", lambda: (calls.append(1), _fake_states(len(calls)))[1], raising=False)
    out = tmp_path / "run"
    assert cli.main(_args(tree, out, "--device", "cpu", "--steps", "2")) == 0
    saved = torch.load(out / "checkpoints" / "step_000001.pt", map_location="cpu", weights_only=True)
    cuda = saved["train_state"]["rng_states"][0]["cuda"]
    assert calls and len(cuda) == 2 and all(torch.equal(a, b) for a, b in zip(cuda, _fake_states(1)))
    restored = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", lambda states: restored.append(list(states)))
    for count, want in ((2, [_fake_states(1)]), (1, [])):  # the same GPU count, then another
        monkeypatch.setattr(torch.cuda, "device_count", lambda c=count: c)
        restored.clear()
        capsys.readouterr()
        args = _args(tree, tmp_path / f"resumed_{count}", "--device", "cpu", "--steps", "2", "--resume",
                     str(out / "checkpoints" / "step_000001.pt"))
        assert cli.main(args) == 0
        assert len(restored) == len(want) and all(torch.equal(a, b) for r, w in zip(restored, want)
                                                  for a, b in zip(r, w))
        note = "CUDA random states for 2 GPU(s), this process sees 1" in capsys.readouterr().err
        assert note == (count == 1)
