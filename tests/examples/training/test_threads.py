"""Thread defaults (mssf_examples/training/threads.py): one intra-op thread for the demo, the CLI and the tests.

benchmarks/threads.py measured why: with 2 threads a demo image pre-training step took 5 s
instead of 0.13 s while one other process kept the 2-core machine busy; with 1 thread it never lost
more than 1.5x. The default used to be 2 in the demo and the CLI (and torch's core count in the tests).
"""

import os
import sys
from pathlib import Path

import pytest
import torch

from mssf_examples.training import threads

pytest.importorskip("spconv")  # the CLI and the demo import the spconv detectors


def test_the_measured_default_is_one_thread():
    assert threads.DEFAULT_THREADS == 1


def test_demo_and_cli_default_to_it():
    sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "examples"))
    import train_demo
    from mssf_examples.cli import commands as cli

    assert train_demo.parse_args([]).threads == 1
    ap = cli.build_parser()
    train = ["train", "--dataset", "vod", "--out", "o"]
    assert ap.parse_args(train).threads == 1
    assert ap.parse_args(["eval", "--checkpoint", "c.pt"]).threads == 1
    assert ap.parse_args(train + ["--threads", "2"]).threads == 2


@pytest.mark.skipif("OMP_NUM_THREADS" in os.environ, reason="an explicit OMP_NUM_THREADS sets the suite's threads")
def test_the_suite_runs_on_one_thread():
    assert torch.get_num_threads() == 1
