"""The projection worked example of docs/conventions.md: the numbers printed in the prose hold.

The page states VoD intrinsics, a centroid, its pixel ``(u, v)``, its normalised ``uv`` and its stride-8
level coordinate ``x_l``. Each printed number is read from the page and compared, to its printed digits,
with the pinhole formula in float64 written here and with ``project_points`` (the library).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from mssf_blocks.functional.geometry import project_points

PAGE = Path(__file__).resolve().parents[2] / "docs" / "conventions.md"


def _number(pattern: str, text: str) -> str:
    m = re.search(pattern, text, re.S)
    assert m, f"docs/conventions.md: the worked example no longer matches {pattern!r}"
    return m.group(1)


def _close(shown: str, value: float) -> None:
    decimals = len(shown.split(".")[1]) if "." in shown else 0
    assert abs(float(shown) - value) <= 0.5 * 10.0 ** -decimals * 1.0001, (shown, value)


def test_projection_worked_example_numbers():
    text = PAGE.read_text(encoding="utf-8")
    fx = float(_number(r"fx = fy = ([\d.]+)", text))
    cx, cy = float(_number(r"`cx = ([\d.]+)`", text)), float(_number(r"`cy = ([\d.]+)`", text))
    w, h = (int(v) for v in re.search(r"image\s+(\d+) x (\d+), sensor x forward", text).groups())
    centroid = [float(v) for v in _number(r"The centroid `\(([-\d., ]+)\)` is camera point", text).split(",")]
    # sensor x forward / y left / z up -> camera x right / y down / z forward
    xc, yc, zc = -centroid[1], -centroid[2], centroid[0]
    u, v = fx * xc / zc + cx, fx * yc / zc + cy
    _close(_number(r"`u = [^=`]+= ([\d.]+)`", text), u)
    _close(_number(r"`v = [^=`]+= ([\d.]+)`", text), v)
    shown_uv = re.search(r"Normalised: `uv = \([^)]*\) = \(([\d.]+), ([\d.]+)\)`", text).groups()
    _close(shown_uv[0], (u + 0.5) / w)
    _close(shown_uv[1], (v + 0.5) / h)
    w8 = int(_number(r"stride-8 level \(`W_l = (\d+)`\)", text))
    assert w8 == w // 8
    _close(_number(r"- 0\.5 = ([\d.]+) = \(", text), (u + 0.5) / 8 - 0.5)

    k = torch.tensor([[fx, 0, cx], [0, fx, cy], [0, 0, 1]], dtype=torch.float64)
    axes = torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]], dtype=torch.float64)
    proj = project_points(torch.tensor([centroid], dtype=torch.float64), torch.zeros(1, dtype=torch.long),
                          (k @ axes)[None, None], (h, w))
    assert proj.valid.all()
    assert proj.pixel[0, 0].tolist() == pytest.approx([u, v], abs=1e-9)
    assert proj.uv[0, 0].tolist() == pytest.approx([(u + 0.5) / w, (v + 0.5) / h], abs=1e-12)
