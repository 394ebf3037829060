"""``python -m mssf_examples.mmdet3d test`` and ``train --resume`` unpickle checkpoints weights-only, with exactly
what mmengine 0.10's checkpoints hold allowed (``mssf_examples.mmdet3d.checkpoints``): a crafted file whose
pickle runs code is refused with an error naming it, and the code does not run. That real checkpoints of the
shipped configs load (``test`` and ``--resume``) is checked by test_mmdet3d_docs.py, which runs the page's
lines, and the allow-list's exactness there too (the unsafe globals of its quick check's checkpoint).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import CONFIGS, require_mmdet3d, write_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")


class _Payload:
    """Unpickling it calls ``exec`` (what a crafted checkpoint does): it writes ``marker``."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').write('ran')",)


def crafted(path: Path, marker: Path) -> Path:
    torch.save({"meta": {"epoch": 1, "note": _Payload(marker)}, "state_dict": {}}, path)
    return path


def test_crafted_checkpoint_is_refused(tmp_path, monkeypatch):
    require_mmdet3d()
    from mssf_blocks.errors import MSSFError
    from mssf_examples.mmdet3d.checkpoints import load_from_local_weights_only
    from mssf_examples.mmdet3d.cli import main

    monkeypatch.delenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", raising=False)
    marker = tmp_path / "ran"
    bad = crafted(tmp_path / "crafted.pth", marker)
    with pytest.raises(MSSFError, match=r"checkpoint: .*crafted\.pth holds objects .*exec.*refused: unpickling"):
        load_from_local_weights_only(str(bad), "cpu")
    data_root = write_tree(tmp_path / "vod", train=1, val=1)
    common = ["--data-root", str(data_root), "--work-dir", str(tmp_path / "wd"), "--image-scale", "160", "100"]
    for args in (["test", str(CONFIGS / "mssf_pointpillars_vod.py"), str(bad)],
                 ["train", str(CONFIGS / "pointpillars_vod_radar.py"), "--resume", str(bad), "--iters", "1"]):
        with pytest.raises(MSSFError, match=r"crafted\.pth holds objects .*refused") as info:
            main(args + common)
        assert "Please file an issue" not in str(info.value)  # ours, not torch's advice
        assert not marker.exists(), args  # the payload never ran
    assert "TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD" not in os.environ  # the entry changes nothing process-wide
    # mmengine's loader is its own again after the entry
    from mmengine.runner.checkpoint import CheckpointLoader

    assert CheckpointLoader._schemes[""].__module__ == "mmengine.runner.checkpoint"


def _mmengine_like_checkpoint(path: Path) -> dict:
    """A checkpoint with every kind of object mmengine 0.10's Runner saves (weights, an optimizer, the
    message hub's HistoryBuffers and numpy scalars, OneCycleParamScheduler's annealing function), built from
    mmengine's own classes: no training, so the loader is checked where mmdet3d's ops do not install too."""
    import numpy as np
    from mmengine.logging import MessageHub
    from mmengine.optim.scheduler.param_scheduler import OneCycleParamScheduler

    net = torch.nn.Linear(3, 2)
    optim = torch.optim.AdamW(net.parameters(), lr=1e-3)
    net(torch.randn(4, 3)).sum().backward()
    optim.step()
    sched = OneCycleParamScheduler(optim, param_name="lr", eta_max=0.01, total_steps=10)
    hub = MessageHub.get_instance("mssf_checkpoint_test")
    hub.update_scalar("train/loss", 0.5)
    hub.update_info("eta", np.float64(12.5))
    ckpt = {"meta": {"epoch": 1, "iter": 3}, "state_dict": net.state_dict(), "optimizer": optim.state_dict(),
            "message_hub": hub.state_dict(), "param_schedulers": [sched.state_dict()]}
    torch.save(ckpt, path)
    return ckpt


@pytest.mark.parametrize("torch_before_2_6", [False, True])
def test_allow_list_on_every_torch(tmp_path, monkeypatch, torch_before_2_6):
    """The same allow-list whichever torch: on torch < 2.6 (mmcv 2.1's own torch 2.1; forced here on a newer
    torch, and real in make test-compat's floor environment) a restricted unpickler enforces it. A checkpoint
    of every kind mmengine saves loads equal; a crafted one is refused and its code does not run."""
    pytest.importorskip("mmengine")
    from mssf_blocks import torch_versions as _compat
    from mssf_blocks.errors import MSSFError
    from mssf_examples.mmdet3d.checkpoints import load_from_local_weights_only

    if torch_before_2_6:
        monkeypatch.setattr(_compat, "TORCH_VERSION", min(_compat.TORCH_VERSION, (2, 5)))
    elif _compat.TORCH_VERSION < (2, 6):
        pytest.skip(f"torch {torch.__version__}: the weights-only path needs torch >= 2.6")
    want = _mmengine_like_checkpoint(tmp_path / "ok.pth")
    got = load_from_local_weights_only(str(tmp_path / "ok.pth"), "cpu")
    assert set(got) == set(want)
    for k, v in want["state_dict"].items():
        assert torch.equal(got["state_dict"][k], v)
    assert got["optimizer"]["state"][0]["exp_avg"].equal(want["optimizer"]["state"][0]["exp_avg"])
    assert got["message_hub"]["runtime_info"]["eta"] == 12.5
    assert got["param_schedulers"][0]["anneal_func"] == want["param_schedulers"][0]["anneal_func"]
    marker = tmp_path / "ran"
    bad = crafted(tmp_path / "crafted.pth", marker)
    with pytest.raises(MSSFError, match=r"crafted\.pth holds objects .*exec.*refused: unpickling"):
        load_from_local_weights_only(str(bad), "cpu")
    assert not marker.exists()
    # a getattr that is not one of mmengine's methods is refused too (the stand-in, not builtins.getattr)
    torch.save({"f": _GetattrPayload()}, tmp_path / "getattr.pth")
    with pytest.raises(MSSFError, match=r"getattr\.pth holds objects"):
        load_from_local_weights_only(str(tmp_path / "getattr.pth"), "cpu")


class _GetattrPayload:
    """Unpickles as ``getattr(numpy.ndarray, 'tofile')`` (a file writer): an allowed class, but not one of the
    methods mmengine keeps."""

    def __reduce__(self):
        import numpy as np

        return getattr, (np.ndarray, "tofile")
