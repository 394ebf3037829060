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
