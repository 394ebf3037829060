"""Cases of the "Common mistakes" table (tests/docs/test_docs_mistakes_table.py): the CLI and the point reader.

``python -m mssf_examples`` runs in this process (:func:`mistakes_registry.cli`) on copies of the generated
VoD tree (tests/examples/helpers/generated_tree.py), each broken one way, as tests/examples/cli/test_misuse_eval_cli.py,
test_point_layout.py and test_cli_image_branch.py do; every run stops at its check, before any training.
"""

from __future__ import annotations

import atexit
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from mistakes_library import _helpers
from mistakes_registry import cli, case, outcome

_SCRATCH = []


def _tree() -> Path:
    """The generated VoD tree, written once per process (a temporary folder removed at exit)."""
    if not _SCRATCH:
        pytest.importorskip("spconv")
        pytest.importorskip("PIL")
        tmp = Path(tempfile.mkdtemp(prefix="mssf-mistakes-"))
        atexit.register(shutil.rmtree, tmp, True)
        _SCRATCH.append(tmp)
        _helpers("generated_tree", "examples/helpers").write_generated_tree(tmp / "vod")
    return _SCRATCH[0] / "vod"


def _copy(name: str) -> Path:
    """A fresh copy of the tree (the mistake is written into it) and its training folder."""
    dst = _SCRATCH[0] / name
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(_tree(), dst)
    return dst


def _train(root: Path, dataset: str = "vod", *extra: str):
    out = _SCRATCH[0] / "out"
    shutil.rmtree(out, ignore_errors=True)
    return ["train", "--dataset", dataset, "--data-root", str(root), "--preset", "tiny", "--steps", "1",
            "--batch-size", "2", "--threads", "1", "--no-progress", "--workers", "0", "--out", str(out), *extra]


def _points(root: Path) -> Path:
    return root / "radar_5frames" / "training" / "velodyne"


@case("CLI: `--out` an existing file")
def _():
    root = _tree()
    pl = _helpers("test_point_layout", "examples/data")

    def out_a_file():
        f = _SCRATCH[0] / "a_file"
        f.write_text("x")
        cli(_train(root)[:-1] + [str(f)])

    def tj4d_points_as_vod():
        vod = _copy("tj4d_as_vod")
        pl._rewrite_points(_points(vod), lambda i: pl.tj4d_points(56, i))
        cli(_train(vod))

    def truncated():
        vod = _copy("truncated")
        path = sorted(_points(vod).glob("*.bin"))[0]
        path.write_bytes(path.read_bytes()[:-6])  # half a float
        cli(_train(vod))

    def unknown_type():
        vod = _copy("zeppelin")
        for f in sorted((vod / "radar_5frames" / "training" / "label_2").iterdir()):
            lines = f.read_text().splitlines()
            if lines:
                f.write_text("\n".join(["Zeppelin " + lines[0].split(" ", 1)[1], *lines[1:]]) + "\n")
        cli(_train(vod))

    def no_p2():
        vod = _copy("no_p2")
        for f in (vod / "radar_5frames" / "training" / "calib").iterdir():
            f.write_text("\n".join(line for line in f.read_text().splitlines() if not line.startswith("P2")))
        cli(_train(vod))

    return outcome(out_a_file, lambda: cli(_train(root / "radar_5frames", "tj4d")), tj4d_points_as_vod, truncated,
                   unknown_type, no_p2)


@case("a point file whose size fits both datasets")
def _():
    root = _tree()
    pl = _helpers("test_point_layout", "examples/data")
    from mssf_examples.data.kitti_io import TJ4D_RADAR, read_points

    def rewritten(name, make, dataset="vod"):
        vod = _copy(name)
        pl._rewrite_points(_points(vod), make)
        if dataset == "tj4d":  # the frames in TJ4DRadSet's layout
            shutil.rmtree(_SCRATCH[0] / f"{name}_tj4d", ignore_errors=True)
            vod = pl._tj4d_tree(vod, _SCRATCH[0] / f"{name}_tj4d")
        cli(_train(vod, dataset))

    def reader():
        f = _SCRATCH[0] / "vod.bin"
        pl._both_widths(pl.vod_points(64, 0)).tofile(f)
        read_points(f, TJ4D_RADAR)

    g = np.random.default_rng(0)
    lidar = lambda i: np.concatenate([g.uniform(-40, 40, (224, 3)), g.uniform(0, 1, (224, 1))], 1).astype("<f4")  # noqa: E731
    return outcome(lambda: rewritten("vod_as_tj4d", lambda i: pl._both_widths(pl.vod_points(64, i)), "tj4d"),
                   lambda: rewritten("tj4d_as_vod2", lambda i: pl._both_widths(pl.tj4d_points(56, i))),
                   lambda: rewritten("neither", lidar),
                   lambda: rewritten("both", lambda i: np.zeros(448, "<f4")),
                   reader)


@case("CLI `train`: a frozen image branch")
def _():
    root = _tree()

    class Built(Exception):
        """Raised in place of training: the detector was built, the mistake passed."""

    def stop(*args, **kwargs):
        raise Built()

    def run():
        from mssf_examples.cli import commands as entry

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(entry, "train_detector", stop)
            cli(["train", "--dataset", "vod", "--data-root", str(root), "--steps", "1", "--batch-size", "2",
                 "--threads", "1", "--no-progress", "--workers", "0", "--no-augment", "--out",
                 str(_SCRATCH[0] / "frozen"), "--detector", "second", "--fusion-blocks", "1"])
    return outcome(run)
