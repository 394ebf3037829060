"""FusionBlock through the shared block checks (``tests/helpers/block_tester.py``): the state-dict round trip
of a block with its sampler and query initialisation (MSDFF + QueryInit), spconv parts as in
``test_fusion_block.py``. FusionBlock's other behaviour: ``test_fusion_block.py``."""

import sys
from pathlib import Path

import pytest
import torch

from mssf_blocks.blocks import FusionBlock, infer_downsample_stride  # noqa: E402
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit  # noqa: E402

from block_tester import BlockTester

sys.path.insert(0, str(Path(__file__).parent))
from test_fusion_block import RANGE_MIN, Doubler, make_scene  # noqa: E402  (skips without spconv)

# Tiny tensors on a shared 2-core machine: OpenMP spinning dominates otherwise (see test_sff).
pytestmark = [pytest.mark.spconv, pytest.mark.usefixtures("one_thread")]


class TestFusionBlock(BlockTester):
    def state_dict_case(self):
        voxels, inputs = make_scene(seed=6, c=8)
        value_dim = None

        def build():
            msdff = MSDFF(6, 8, value_dim, num_heads=2, num_levels=2, num_points=2)
            qi = QueryInit(8, 6, 8, (*RANGE_MIN, 10.0, 4.0, 1.0))
            with torch.no_grad():  # at Deformable-DETR init the query has no effect (zero offset/attention weights)
                msdff.sampling_offsets.weight.normal_(0.0, 0.1)
            return FusionBlock(msdff, blocks=Doubler(), query_init=qi)

        return build, lambda m: m.eval()(voxels, inputs).features
