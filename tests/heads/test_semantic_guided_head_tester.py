"""SemanticGuidedHead through the shared block checks (``tests/helpers/block_tester.py``): the forward
against the MLP written out by hand (eval mode, non-trivial running statistics) on every device, float64
gradcheck, the state-dict round trip and a compile smoke. The head's other behaviour:
``test_semantic_guided_head.py``."""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import nn

from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.sparse_voxels import SparseVoxels

from block_tester import BlockTester, Reference

sys.path.insert(0, str(Path(__file__).parent))
from test_semantic_guided_head import make_voxels, manual_mlp  # noqa: E402


def _run(head, vox):
    out, scores, logits = head(vox, return_logits=True)
    assert out.spatial_shape == vox.spatial_shape
    out2, scores2 = head(vox)
    return logits, scores, out.features, out.coords, out2.features


class TestSemanticGuidedHead(BlockTester):
    compile_smoke = True

    def reference(self, case):
        head = SemanticGuidedHead(4, hidden=(8, 5)).double()
        with torch.no_grad():  # non-trivial running statistics
            for m in head.mlp:
                if isinstance(m, nn.BatchNorm1d):
                    m.running_mean.uniform_(-0.5, 0.5)
                    m.running_var.uniform_(0.5, 2.0)
                    m.weight.uniform_(0.5, 1.5)
                    m.bias.uniform_(-0.2, 0.2)
        head.eval()
        vox = make_voxels(dtype=torch.float64)
        exp_logits = manual_mlp(head, vox.features)
        scores = 1 / (1 + torch.exp(-exp_logits))
        return Reference(head, lambda d: (vox.to(d),), _run,
                         (exp_logits, scores, vox.features * scores[:, None], vox.coords, vox.features * scores[:, None]))

    def gradcheck(self, case):
        head = SemanticGuidedHead(3, hidden=(4,)).double().eval()
        coords = torch.tensor([[0, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=torch.int32)

        def fn(f):
            vox = SparseVoxels(f, coords, (1, 2, 2), 1, voxel_size=(1.0, 1.0, 1.0), point_range_min=(0.0, 0.0, 0.0))
            out, scores = head(vox)
            return out.features, scores

        return fn, [torch.randn(3, 3, dtype=torch.float64)]

    def state_dict_case(self):
        vox = make_voxels()
        return lambda: SemanticGuidedHead(4, hidden=(8,)), lambda m: m.eval()(vox)[1]
