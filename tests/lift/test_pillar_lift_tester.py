"""PillarLift through the shared block checks (``tests/helpers/block_tester.py``): float64 gradcheck of the
lift and its sum back to the BEV map, and the state-dict round trip (the height embedding). The lift
against per-row loops and the other behaviour: ``test_pillar_lift.py``."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from mssf_blocks.lift import HeightEmbedding, PillarLift

from block_tester import BlockTester

sys.path.insert(0, str(Path(__file__).parent))
from test_pillar_lift import scene  # noqa: E402


class TestPillarLift(BlockTester):
    def gradcheck(self, case):
        vox = scene()
        lift = PillarLift(2, 3, stride=2).double()
        with torch.no_grad():
            lift.height_embedding.weight.normal_()

        bev = torch.randn(2, 2, 2, 3, dtype=torch.float64)
        return (lambda b: lift.to_bev(lift(b, vox))), [bev]

    def state_dict_case(self):
        vox = scene()
        bev = torch.randn(2, 3, 4, 6, dtype=torch.float64)

        def build():
            lift = PillarLift(channels=3, num_z=3, stride=1).double()
            with torch.no_grad():
                lift.height_embedding.weight.normal_()  # zero at initialisation: give it values of its own
            return lift

        return build, lambda m: m(bev, vox).features
