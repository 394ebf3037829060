"""SFF through the shared block checks (``tests/helpers/block_tester.py``): the sampled features and the
output against ``fusion_references`` on every device, float64 gradcheck in train mode, the state-dict round
trip and a compile smoke. SFF's other behaviour: ``test_sff.py``."""

import pytest
import torch

from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit, sample_at_projection

from block_tester import BlockTester, Reference
from fusion_references import D64, make_projection, randomize_norm, ref_bn_eval, reference_sff_sample, scene

# Tiny tensors: with 2 OpenMP threads on a loaded 2-core machine, each train-mode batch_norm call
# spins for ~10-50 ms (measured), which makes gradcheck 100x slower. One thread is plenty here.
pytestmark = pytest.mark.usefixtures("one_thread")


class TestSFF(BlockTester):
    compile_smoke = True

    def reference(self, case):
        gen = torch.Generator().manual_seed(0)
        levels, uv, valid, bidx = scene(gen)
        sff = SFF([3, 2], 4, dtype=D64).eval()
        randomize_norm(sff.norm, gen)
        sampled = reference_sff_sample(levels, uv, valid, bidx)
        y = ref_bn_eval(sampled @ sff.linear.weight.T + sff.linear.bias, sff.norm)
        y[~valid.any(1)] = 0.0
        return Reference(sff, lambda d: ([l.to(d) for l in levels], make_projection(uv, valid, bidx, d)),
                         lambda m, lv, proj: (m.sample(lv, proj), m(lv, proj)), (sampled, y))

    def gradcheck(self, case):
        # Train-mode BN normalises with the statistics of the visible voxels of this very batch: a smooth,
        # deterministic function of the inputs (5 visible voxels), so gradcheck is valid; running-stat
        # updates between calls do not affect train-mode outputs.
        gen = torch.Generator().manual_seed(1)
        levels, uv, valid, bidx = scene(gen, n=6, chans=(2, 1), sizes=((3, 4), (2, 3)))
        sff = SFF([2, 1], 3, dtype=D64).train()
        assert int(valid.any(1).sum()) >= 3

        def fn(l0, l1, uv_):
            return sff([l0, l1], make_projection(uv_, valid, bidx))

        return fn, (levels[0], levels[1], uv)

    def state_dict_case(self):
        gen = torch.Generator().manual_seed(2)
        levels, uv, valid, bidx = scene(gen)

        def build():
            sff = SFF([3, 2], 4, dtype=D64).eval()
            randomize_norm(sff.norm, gen)  # running statistics and affine of its own (next draws of gen)
            return sff

        return build, lambda m: m(levels, make_projection(uv, valid, bidx))
