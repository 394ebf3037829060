"""benchmarks/_common.py's per-round spread, on hand-worked timings."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from _common import round_spread  # noqa: E402


def test_round_spread_pairs_rounds():
    # per-round ratios 2/1 = 2, 9/3 = 3, 5/2 = 2.5: the range 2-3 behind the medians' ratio 5/2
    assert round_spread([2.0, 9.0, 5.0], [1.0, 3.0, 2.0]) == "2.00-3.00"
    # round by round, 4/1 and 1/4 (pairing the sorted timings instead would give 1/1 and 4/4)
    assert round_spread([4.0, 1.0], [1.0, 4.0]) == "0.25-4.00"


def test_round_spread_needs_the_same_rounds():
    with pytest.raises(ValueError):
        round_spread([1.0, 2.0], [1.0])
