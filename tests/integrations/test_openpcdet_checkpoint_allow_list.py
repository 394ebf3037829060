"""``mssf_examples.training.checkpoint_allow_list``: on torch < 2.6 (forced here on a newer torch; real in make
test-compat's floor environment, torch 2.1.2) the framework entries' ``torch.load`` unpickles through an
allow-list. A checkpoint shaped like OpenPCDet's (weights, an optimizer state with numpy scalars) loads equal;
a crafted one is refused with an error naming the file and its code does not run; ``torch.load`` is torch's
own again afterwards."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest
import torch

from mssf_blocks import torch_versions as _compat
from mssf_blocks.errors import MSSFError
from mssf_examples.training.checkpoint_allow_list import restricted_torch_load
from mssf_examples.openpcdet.__main__ import _HOLDS, _INSTEAD, checkpoint_numpy_globals


class _Payload:
    """Unpickling it calls ``exec``: it writes ``marker``."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').write('ran')",)


def _openpcdet_like(path: Path) -> dict:
    net = torch.nn.Linear(3, 2)
    optim = torch.optim.Adam(net.parameters(), lr=1e-3)
    net(torch.randn(4, 3)).sum().backward()
    optim.step()
    state = optim.state_dict()
    state["param_groups"][0]["lr"] = np.float64(0.003)  # OpenPCDet's one-cycle schedule writes numpy scalars
    ckpt = {"epoch": 3, "it": 12, "model_state": net.state_dict(), "optimizer_state": state, "version": "pcdet+x"}
    torch.save(ckpt, path)
    return ckpt


@pytest.mark.parametrize("torch_before_2_6", [True, False])
def test_framework_loads_go_through_the_allow_list(tmp_path, monkeypatch, torch_before_2_6):
    if torch_before_2_6:
        monkeypatch.setattr(_compat, "TORCH_VERSION", min(_compat.TORCH_VERSION, (2, 5)))
    elif _compat.TORCH_VERSION < (2, 6):
        pytest.skip(f"torch {torch.__version__} is before 2.6")
    want = _openpcdet_like(tmp_path / "ok.pth")
    marker = tmp_path / "ran"
    torch.save({"epoch": 1, "model_state": {}, "note": _Payload(marker)}, tmp_path / "bad.pth")
    original = torch.load
    # torch >= 2.6: the entry's add_safe_globals of the same list (here scoped to the test)
    allow = (contextlib.nullcontext() if torch_before_2_6
             else torch.serialization.safe_globals(checkpoint_numpy_globals()))
    with allow, restricted_torch_load(checkpoint_numpy_globals(), _HOLDS, _INSTEAD):
        got = torch.load(str(tmp_path / "ok.pth"), map_location="cpu")  # as OpenPCDet calls it
        if torch_before_2_6:
            with pytest.raises(MSSFError, match=r"checkpoint: .*bad\.pth holds objects .*exec.*refused"):
                torch.load(str(tmp_path / "bad.pth"), map_location="cpu")
        else:  # torch >= 2.6 itself refuses (weights_only by default), with the numpy scalars allow-listed
            with pytest.raises(Exception, match="exec"):
                torch.load(str(tmp_path / "bad.pth"), map_location="cpu")
    assert torch.load is original
    assert not marker.exists()
    assert got["epoch"] == 3 and got["version"] == "pcdet+x"
    for k, v in want["model_state"].items():
        assert torch.equal(got["model_state"][k], v)
    assert got["optimizer_state"]["param_groups"][0]["lr"] == 0.003
    assert torch.equal(got["optimizer_state"]["state"][0]["exp_avg"], want["optimizer_state"]["state"][0]["exp_avg"])
