"""examples/plot_diagnostics.py (the figure in docs/diagnostics.md) runs and writes a PNG."""

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("matplotlib")

SCRIPT = Path(__file__).resolve().parents[3] / "examples" / "plot_diagnostics.py"


def test_plot_diagnostics_writes_png(tmp_path):
    out = tmp_path / "blur.png"
    proc = subprocess.run([sys.executable, str(SCRIPT), "--steps", "10", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert out.exists() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert out.stat().st_size > 10_000  # a real figure, not an empty canvas
