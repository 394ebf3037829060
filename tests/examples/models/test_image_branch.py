import os
import subprocess
import sys

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks.errors import MSSFError
from mssf_blocks.testing import assert_close
from mssf_examples.models.image_branch import FPN, BasicBlock, Bottleneck, ImageBranch, ResNet, SubsampledConv1x1


def _bn(x, bn):
    return (x - bn.running_mean[:, None, None]) / torch.sqrt(bn.running_var[:, None, None] + bn.eps) * bn.weight[
        :, None, None
    ] + bn.bias[:, None, None]


def _randomise_bn(m):
    for mod in m.modules():
        if isinstance(mod, torch.nn.BatchNorm2d):
            mod.running_mean.uniform_(-0.3, 0.3)
            mod.running_var.uniform_(0.5, 1.5)
            mod.weight.data.uniform_(0.5, 1.5)
            mod.bias.data.uniform_(-0.3, 0.3)


def test_basic_block_matches_functional_reference():
    torch.manual_seed(0)
    blk = BasicBlock(4, 6, stride=2).double().eval()
    _randomise_bn(blk)
    x = torch.randn(2, 4, 9, 7, dtype=torch.float64)
    y = F.relu(_bn(F.conv2d(x, blk.conv1.weight, stride=2, padding=1), blk.bn1))
    y = _bn(F.conv2d(y, blk.conv2.weight, padding=1), blk.bn2)
    sc = _bn(F.conv2d(x, blk.downsample[0].weight, stride=2), blk.downsample[1])
    assert_close(blk(x), F.relu(y + sc))


def test_bottleneck_matches_functional_reference():
    torch.manual_seed(1)
    blk = Bottleneck(8, 2, stride=1).double().eval()  # 8 == 2 * 4: identity shortcut
    _randomise_bn(blk)
    assert blk.downsample is None
    x = torch.randn(1, 8, 5, 5, dtype=torch.float64)
    y = F.relu(_bn(F.conv2d(x, blk.conv1.weight), blk.bn1))
    y = F.relu(_bn(F.conv2d(y, blk.conv2.weight, padding=1), blk.bn2))
    y = _bn(F.conv2d(y, blk.conv3.weight), blk.bn3)
    assert_close(blk(x), F.relu(y + x))


def test_fpn_matches_hand_computation():
    torch.manual_seed(2)
    fpn = FPN([3, 5], out_channels=4, num_outs=3).double()
    a = torch.randn(1, 3, 8, 8, dtype=torch.float64)
    b = torch.randn(1, 5, 4, 4, dtype=torch.float64)
    outs = fpn([a, b])
    la = F.conv2d(a, fpn.lateral_convs[0].conv.weight, fpn.lateral_convs[0].conv.bias)
    lb = F.conv2d(b, fpn.lateral_convs[1].conv.weight, fpn.lateral_convs[1].conv.bias)
    la = la + lb.repeat_interleave(2, 2).repeat_interleave(2, 3)  # nearest upsampling by 2
    pa = F.conv2d(la, fpn.fpn_convs[0].conv.weight, fpn.fpn_convs[0].conv.bias, padding=1)
    pb = F.conv2d(lb, fpn.fpn_convs[1].conv.weight, fpn.fpn_convs[1].conv.bias, padding=1)
    assert_close(outs[0], pa)
    assert_close(outs[1], pb)
    assert_close(outs[2], pb[:, :, ::2, ::2])


@pytest.mark.parametrize("depth", [18, 50])
def test_image_branch_shapes_and_strides(depth):
    br = ImageBranch(depth=depth, base_channels=8, fpn_channels=16, num_outs=4).eval()
    out = br(torch.randn(2, 3, 3, 64, 96))
    assert [tuple(o.shape) for o in out] == [(2, 3, 16, 64 // s, 96 // s) for s in (4, 8, 16, 32)]
    assert ImageBranch.level_strides(4) == (4, 8, 16, 32)


def test_cameras_are_independent():
    torch.manual_seed(3)
    br = ImageBranch(depth=18, base_channels=4, fpn_channels=8).eval()
    x = torch.randn(1, 2, 3, 32, 32)
    ref = br(x)
    x2 = x.clone()
    x2[:, 1] = torch.randn(3, 32, 32)
    out = br(x2)
    for r, o in zip(ref, out):
        assert_close(o[:, 0], r[:, 0])
        assert not torch.allclose(o[:, 1], r[:, 1])


def test_state_dict_round_trip_and_torchvision_names():
    torch.manual_seed(4)
    a = ImageBranch(depth=18, base_channels=4, fpn_channels=8).eval()
    _randomise_bn(a)
    b = ImageBranch(depth=18, base_channels=4, fpn_channels=8).eval()
    b.load_state_dict(a.state_dict())
    x = torch.randn(1, 1, 3, 32, 32)
    for u, w in zip(a(x), b(x)):
        assert_close(u, w)
    keys = set(a.state_dict())
    for k in ("backbone.conv1.weight", "backbone.bn1.running_var", "backbone.layer2.0.downsample.0.weight",
              "neck.lateral_convs.0.conv.weight", "neck.fpn_convs.3.conv.bias"):
        assert k in keys


def test_channels_last_branch_same_values_row_layout_and_msdff_reads_rows():
    # channels_last=True (the default): the same features as the NCHW branch (float64, same weights),
    # each level with contiguous per-pixel channel rows, which MSDFF's sampler reads as a free
    # (pixels, C) table.
    from mssf_blocks.functional.deform.touched.plans import _row_table

    torch.manual_seed(5)
    a = ImageBranch(depth=18, base_channels=4, fpn_channels=8, channels_last=False).double().eval()
    _randomise_bn(a)
    b = ImageBranch(depth=18, base_channels=4, fpn_channels=8).double().eval()
    b.load_state_dict(a.state_dict())
    x = torch.randn(2, 2, 3, 64, 96, dtype=torch.float64)
    for u, w in zip(a(x), b(x)):
        assert_close(w, u)
        assert w.stride(2) == 1 and u.stride(2) != 1
        assert _row_table(w.reshape(4, 1, *w.shape[2:])) is not None
        assert _row_table(u.reshape(4, 1, *u.shape[2:])) is None


def test_frozen_branch_has_no_grad_and_fixed_bn():
    br = ImageBranch(depth=18, base_channels=4, fpn_channels=8, frozen=True)
    br.train()
    stats = br.backbone.bn1.running_mean.clone()
    out = br(torch.randn(1, 1, 3, 32, 32))
    assert not out[0].requires_grad
    assert all(not p.requires_grad for p in br.parameters())
    assert torch.equal(br.backbone.bn1.running_mean, stats)


def test_partial_freezing():
    r = ResNet(18, 4, frozen_stages=1)
    r.train()
    assert not r.conv1.weight.requires_grad and not r.layer1[0].conv1.weight.requires_grad
    assert r.layer2[0].conv1.weight.requires_grad
    assert not r.layer1[0].bn1.training and r.layer2[0].bn1.training


def test_bad_settings_and_input():
    with pytest.raises(MSSFError, match="depth"):
        ResNet(depth=20)
    with pytest.raises(MSSFError, match="images"):
        ImageBranch(depth=18, base_channels=4, fpn_channels=8)(torch.randn(1, 3, 32, 32))


@pytest.mark.parametrize("stride", [1, 2, (2, 1)])
@pytest.mark.parametrize("channels_last", [False, True])
def test_subsampled_conv1x1_is_the_strided_1x1_convolution(stride, channels_last):
    torch.manual_seed(0)
    conv = SubsampledConv1x1(3, 5, stride, bias=True).double()
    plain = torch.nn.Conv2d(3, 5, 1, stride, bias=True).double()
    assert list(conv.state_dict()) == list(plain.state_dict())  # checkpoints load unchanged
    plain.load_state_dict(conv.state_dict())
    x = torch.randn(2, 3, 9, 8, dtype=torch.float64)
    if channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    x.requires_grad_(True)
    grad = torch.randn_like(plain(x))
    ours = torch.autograd.grad(conv(x), [x, conv.weight, conv.bias], grad)
    ref = torch.autograd.grad(plain(x), [x, plain.weight, plain.bias], grad)
    assert conv(x).shape == plain(x).shape
    torch.testing.assert_close(conv(x), plain(x), rtol=0, atol=1e-12)
    for a, b in zip(ours, ref):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_resnet_shortcuts_subsample_and_the_demo_step_survives():
    # The shortcut projections are SubsampledConv1x1; the demo's first image pre-training step (its
    # branch, a batch of 8 at 160 x 256, channels-last) ran in a fresh interpreter: with nn.Conv2d's
    # strided 1 x 1 it died of a heap corruption in oneDNN on some CPUs (see SubsampledConv1x1).
    branch = ImageBranch(18, 4, 8, 4)
    shortcuts = [m.downsample[0] for m in branch.modules() if isinstance(m, BasicBlock) and m.downsample is not None]
    assert shortcuts and all(type(c) is SubsampledConv1x1 for c in shortcuts)
    code = (
        "import torch\n"
        "from mssf_examples.models.image_branch import ImageBranch\n"
        "torch.set_num_threads(1); torch.manual_seed(0)\n"
        "branch = ImageBranch(18, 4, 8, 4)\n"
        "feats = branch(torch.rand(8, 1, 3, 160, 256))\n"
        "sum(f.square().mean() for f in feats).backward()\n"
        "print('ok')\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0 and run.stdout.strip() == "ok", (run.returncode, run.stderr[-2000:])
