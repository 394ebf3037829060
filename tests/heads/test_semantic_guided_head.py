"""Tests of SemanticGuidedHead (module wrapper over the functional head)."""

from __future__ import annotations


import pytest
import torch
from torch import nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.heads import sigmoid_focal_loss
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.sparse_voxels import SparseVoxels
from mssf_blocks.testing import assert_close, gradcheck64


def make_voxels(n=6, c=4, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    coords = torch.stack(
        [torch.randint(0, 2, (n,), generator=g), torch.zeros(n, dtype=torch.long),
         torch.arange(n) % 4, torch.arange(n) // 4], dim=1).int()
    feats = torch.randn(n, c, generator=g, dtype=dtype)
    return SparseVoxels(feats, coords, (1, 4, 4), 2, voxel_size=(0.5, 0.5, 1.0), point_range_min=(0.0, 0.0, 0.0))


def manual_mlp(head, x):
    """The MLP by hand from the parameters (eval mode: BN uses running statistics)."""
    h = x
    linears = [m for m in head.mlp if isinstance(m, nn.Linear)]
    norms = [m for m in head.mlp if isinstance(m, nn.BatchNorm1d)]
    for lin, bn in zip(linears, norms):
        h = h @ lin.weight.T
        h = (h - bn.running_mean) / torch.sqrt(bn.running_var + bn.eps) * bn.weight + bn.bias
        h = torch.clamp(h, min=0)
    return (h @ head.classifier.weight.T + head.classifier.bias).squeeze(1)


def test_default_structure():
    head = SemanticGuidedHead(4)
    kinds = [type(m).__name__ for m in head.mlp]
    assert kinds == ["Linear", "BatchNorm1d", "ReLU"] * 2
    assert head.mlp[0].out_features == 256 and head.mlp[3].out_features == 256
    # the forward against the MLP by hand (manual_mlp), on every device: test_semantic_guided_head_tester.py


def test_ablation_switches():
    vox = make_voxels()
    head = SemanticGuidedHead(4, hidden=(8,), use_weighting=False).eval()
    out, scores = head(vox)
    assert out is vox and scores.shape == (6,)
    head = SemanticGuidedHead(4, hidden=(8,), use_loss=False)
    out, scores, logits = head(vox, return_logits=True)
    loss = head.loss(logits, torch.ones(6))
    assert float(loss.detach()) == 0.0 and loss.requires_grad
    loss.backward()  # connected to the graph: every parameter gets a (zero) gradient
    assert all(p.grad is not None for p in head.parameters())


def test_loss_matches_functional_and_boxes_path():
    head = SemanticGuidedHead(4, hidden=(8,))
    vox = make_voxels()
    _, _, logits = head(vox, return_logits=True)
    labels = torch.tensor([1.0, 0, 0, 1, 0, 0])
    ignore = torch.tensor([False, True, False, False, False, False])
    assert_close(head.loss(logits, labels, ignore), sigmoid_focal_loss(logits, labels, ignore))
    centres = vox.voxel_centers()
    box = torch.cat([centres[0], torch.tensor([0.2, 0.2, 0.2, 0.0])])[None]
    gt = [box[:0], box[:0]]
    gt[int(vox.coords[0, 0])] = box
    l1 = head.loss_from_boxes(logits, centres, vox.batch_index, gt)
    lab = torch.zeros(6)
    lab[0] = 1
    assert_close(l1, sigmoid_focal_loss(logits, lab))


def test_prior_prob_sets_initial_scores():
    head = SemanticGuidedHead(4, hidden=(), prior_prob=0.01)
    with torch.no_grad():
        head.classifier.weight.zero_()
    _, scores = head(make_voxels())
    assert_close(scores, torch.full((6,), 0.01), dtype=torch.float32)


# float64 gradcheck and the state-dict round trip: test_semantic_guided_head_tester.py


def test_permutation_equivariance_eval():
    head = SemanticGuidedHead(4, hidden=(8,)).eval()
    vox = make_voxels()
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    out, s = head(vox)
    out_p, s_p = head(vox.replace(features=vox.features[perm], coords=vox.coords[perm]))
    assert_close(s_p, s[perm])
    assert_close(out_p.features, out.features[perm])


def test_empty_and_single_voxel():
    head = SemanticGuidedHead(4, hidden=(8,))
    empty = SparseVoxels(torch.zeros(0, 4), torch.zeros(0, 4, dtype=torch.int32), (1, 2, 2), 1,
                         voxel_size=(1.0, 1.0, 1.0), point_range_min=(0.0, 0.0, 0.0))
    out, scores, logits = head(empty, return_logits=True)
    assert out.features.shape == (0, 4) and scores.shape == (0,)
    head.loss(logits, torch.zeros(0)).backward()
    one = make_voxels(n=1)
    with pytest.raises(MSSFError, match="voxels"):
        head(one)
    assert head.eval()(one)[1].shape == (1,)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"in_channels": 0}, "in_channels"),
        ({"in_channels": 4, "hidden": (8, -1)}, "hidden"),
        ({"in_channels": 4, "hidden": 8}, "hidden"),
        ({"in_channels": 4, "use_loss": "yes"}, "use_loss"),
        ({"in_channels": 4, "prior_prob": 1.0}, "prior_prob"),
    ],
)
def test_bad_settings(kwargs, match):
    with pytest.raises(MSSFError, match=match):
        SemanticGuidedHead(**kwargs)


def test_bad_data():
    head = SemanticGuidedHead(4, hidden=(8,))
    with pytest.raises(MSSFError, match="voxels"):
        head(torch.zeros(3, 4))
    with pytest.raises(MSSFError, match="features"):
        head(make_voxels(c=5))
    with pytest.raises(MSSFError, match="dtype"):
        head(make_voxels(dtype=torch.float64))
    _, _, logits = head(make_voxels(), return_logits=True)
    with pytest.raises(MSSFError, match="targets"):
        head.loss(logits, torch.ones(5))


def test_repr():
    a = SemanticGuidedHead(4, hidden=(8,))
    assert "use_weighting=True" in repr(a)
