"""Smoke test of ``examples/real_frame.py`` on VoD frame 00549 (skips without ../shared/realdata).

The printed counts are checked against an independent numpy computation: points in the grid range,
unique voxels at strides 1, 2, 4, and how many voxel centroids project into the image.
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[3] / "examples" / "real_frame.py"
VOXEL = np.array([0.05, 0.05, 0.125])
LO = np.array([0.0, -25.6, -3.0])
HI = np.array([51.2, 25.6, 2.0])
H, W = 1216, 1936


def _lidar2img(calib_path: Path) -> np.ndarray:
    m = {}
    for line in calib_path.read_text().splitlines():
        key, _, vals = line.partition(":")
        if vals.split():
            m[key] = np.array(vals.split(), dtype=np.float64)
    r0 = np.eye(4)
    r0[:3, :3] = m["R0_rect"].reshape(3, 3)
    tr = np.eye(4)
    tr[:3] = m["Tr_velo_to_cam"].reshape(3, 4)
    return m["P2"].reshape(3, 4) @ r0 @ tr


def _reference(root: Path, fid: str):
    pts = np.fromfile(root / "radar/velodyne" / f"{fid}.bin", dtype="<f4").reshape(-1, 7).astype(np.float64)
    l2i = _lidar2img(root / "radar/calib" / f"{fid}.txt")

    def in_image(xyz):
        cam = np.concatenate([xyz, np.ones((len(xyz), 1))], 1) @ l2i.T
        d = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = cam[:, 0] / d, cam[:, 1] / d
        return (d > 1e-5) & (u >= -0.5) & (u <= W - 0.5) & (v >= -0.5) & (v <= H - 0.5)

    inside = np.all((pts[:, :3] >= LO) & (pts[:, :3] < HI), axis=1)
    xyz = pts[inside, :3]
    idx = np.floor((xyz - LO) / VOXEL).astype(np.int64)
    out = {"points": len(pts), "in_image": int(in_image(pts[:, :3]).sum()), "in_range": int(inside.sum())}
    for s in (1, 2, 4):
        groups = {}
        for key, p in zip(map(tuple, idx // s), xyz):
            groups.setdefault(key, []).append(p)
        centroids = np.array([np.mean(g, axis=0) for g in groups.values()])
        out[s] = (len(groups), int(in_image(centroids).sum()))
    return out


@pytest.mark.realdata
def test_real_frame_script(realdata_root, tmp_path):
    root = realdata_root / "vod"
    if not root.is_dir():
        pytest.skip(f"VoD frames not found at {root}")
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--data-root", str(root), "--frame", "00549", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=300,
    )
    out = proc.stdout
    assert proc.returncode == 0, f"stdout:\n{out}\nstderr:\n{proc.stderr}"
    png = tmp_path / "real_frame_00549.png"
    assert png.is_file() and png.stat().st_size > 10_000, out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    ref = _reference(root, "00549")
    assert f"frame 00549: {ref['points']} points x 7 features" in out, out
    assert f"{ref['in_image']} points project inside the image" in out, out
    assert f": {ref['in_range']} points inside" in out, out
    for s in (1, 2, 4):
        m = re.search(rf"^stride {s}: voxels=(\d+) valid=(\d+)", out, re.M)
        assert m, out
        assert (int(m.group(1)), int(m.group(2))) == ref[s], (s, m.group(0), ref[s], out)
        # voxels seen by no camera get exact-zero image features (when the fusion modules are there)
        for op in ("sff", "msdff"):
            z = re.search(rf"^stride {s} {op}: .* zero rows (\d+)", out, re.M)
            if z:
                assert int(z.group(1)) == ref[s][0] - ref[s][1], (s, op, z.group(0), ref[s], out)
    assert ref[1][0] > 100 and 0 < ref[1][1] < ref[1][0]


def test_real_frame_missing_root_is_a_clear_error(tmp_path):
    spec = importlib.util.spec_from_file_location("real_frame_example", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    with pytest.raises(SystemExit, match="not found"):
        mod.run(tmp_path / "missing", "00549", tmp_path / "out")


def test_real_frame_without_matplotlib_names_the_extra(tmp_path, monkeypatch):
    """The figure needs matplotlib (the ``plot`` extra, not ``examples``): without it the script says so
    before reading any frame, instead of failing with a traceback after the work."""
    spec = importlib.util.spec_from_file_location("real_frame_example_nompl", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError
    ran = []
    monkeypatch.setattr(mod, "run", lambda *a, **k: ran.append(a))
    with pytest.raises(SystemExit, match=r"matplotlib.*mssf-blocks\[plot\]"):
        mod.main(["--data-root", str(tmp_path), "--out", str(tmp_path / "out")])
    assert not ran
