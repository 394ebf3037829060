"""Image branch: a ResNet backbone (He et al., CVPR 2016) and an FPN neck (Lin et al., CVPR 2017).

The paper uses ResNet-50 + FPN (initialised from HTC and frozen). Nothing is downloaded here: load
your own weights with ``load_state_dict``. Parameter names follow the usual layouts so that existing
checkpoints map with little or no renaming: the ResNet uses torchvision's names (``conv1``, ``bn1``,
``layer1.0.conv1``, ``layer1.0.downsample.0`` ...), the FPN uses mmdet's (``lateral_convs.0.conv``,
``fpn_convs.0.conv``); an mmdet checkpoint maps with the prefixes ``img_backbone.`` -> ``backbone.``
and ``img_neck.`` -> ``neck.``.
"""

from __future__ import annotations

from typing import List, Sequence, Tuple, Type

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.errors import MSSFError

__all__ = ["BasicBlock", "Bottleneck", "SubsampledConv1x1", "ResNet", "FPN", "ImageBranch", "RESNET_LAYERS"]

#: blocks per stage for every supported depth.
RESNET_LAYERS = {18: (2, 2, 2, 2), 34: (3, 4, 6, 3), 50: (3, 4, 6, 3), 101: (3, 4, 23, 3), 152: (3, 8, 36, 3)}


class SubsampledConv1x1(nn.Conv2d):
    """A 1 x 1 convolution with a stride (the ResNet shortcut's projection), computed as the stride-1
    convolution of every ``stride``-th pixel: the same arithmetic (each output pixel is one input
    pixel's channels times the weight) and the same parameters (``weight``, ``bias``) as
    ``nn.Conv2d(in, out, 1, stride)``, so checkpoints load unchanged.

    Why: the weight gradient of a strided 1 x 1 convolution on channels-last memory corrupts the heap
    in the oneDNN of torch 2.13's CPU build on some CPUs (measured on an AMD EPYC of family 25 with
    AVX-512: segmentation fault for a batch of 8 at 40 x 64 pixels with 4 or 8 input channels, not at
    16; fine with ``ONEDNN_MAX_CPU_ISA=SSE41`` or with oneDNN off), which killed ``make demo`` at its
    first image pre-training step. Its stride-1 kernel is unaffected; the subsampled view costs a copy
    of a quarter of the input.
    """

    def __init__(self, in_channels: int, out_channels: int, stride: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 1, stride, bias=bias)

    def forward(self, x: Tensor) -> Tensor:
        sy, sx = self.stride
        return F.conv2d(x[..., ::sy, ::sx], self.weight, self.bias)


class BasicBlock(nn.Module):
    """Two 3x3 convs with an identity (or 1x1 projection) shortcut."""

    expansion = 1

    def __init__(self, in_channels: int, channels: int, stride: int = 1, norm_layer: Type[nn.Module] = nn.BatchNorm2d):
        super().__init__()
        out = channels * self.expansion
        self.conv1 = nn.Conv2d(in_channels, channels, 3, stride, 1, bias=False)
        self.bn1 = norm_layer(channels)
        self.conv2 = nn.Conv2d(channels, out, 3, 1, 1, bias=False)
        self.bn2 = norm_layer(out)
        self.downsample = None
        if stride != 1 or in_channels != out:
            self.downsample = nn.Sequential(SubsampledConv1x1(in_channels, out, stride), norm_layer(out))

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        return F.relu(y + identity)


class Bottleneck(nn.Module):
    """1x1 - 3x3 (strided, as torchvision / mmdet "pytorch" style) - 1x1 with expansion 4."""

    expansion = 4

    def __init__(self, in_channels: int, channels: int, stride: int = 1, norm_layer: Type[nn.Module] = nn.BatchNorm2d):
        super().__init__()
        out = channels * self.expansion
        self.conv1 = nn.Conv2d(in_channels, channels, 1, bias=False)
        self.bn1 = norm_layer(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, stride, 1, bias=False)
        self.bn2 = norm_layer(channels)
        self.conv3 = nn.Conv2d(channels, out, 1, bias=False)
        self.bn3 = norm_layer(out)
        self.downsample = None
        if stride != 1 or in_channels != out:
            self.downsample = nn.Sequential(SubsampledConv1x1(in_channels, out, stride), norm_layer(out))

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return F.relu(y + identity)


class ResNet(nn.Module):
    """ResNet backbone returning the outputs of the requested stages.

    Args:
        depth: 18, 34, 50, 101 or 152.
        base_channels: width of the stem and of stage 1 (64 in the standard nets); stage ``i`` has
            ``base_channels * 2**i`` (times 4 for bottlenecks) output channels.
        out_indices: which stages (0..3) to return; stage ``i`` has stride ``4 * 2**i``.
        frozen_stages: ``-1`` freezes nothing, ``0`` the stem, ``k`` the stem and stages ``0..k-1``
            (parameters get ``requires_grad=False`` and their BatchNorms stay in eval mode).
        norm_eval: keep every BatchNorm in eval mode during training (common with small batches).
        norm_layer: 2D normalisation type.

    Shapes:
        - x ``(B, 3, H, W)`` -> list of ``(B, C_i, H / s_i, W / s_i)`` for ``i`` in ``out_indices``.
    """

    def __init__(
        self,
        depth: int = 50,
        base_channels: int = 64,
        out_indices: Sequence[int] = (0, 1, 2, 3),
        frozen_stages: int = -1,
        norm_eval: bool = False,
        norm_layer: Type[nn.Module] = nn.BatchNorm2d,
    ) -> None:
        super().__init__()
        if depth not in RESNET_LAYERS:
            raise MSSFError(f"depth: expected one of {sorted(RESNET_LAYERS)}, got {depth!r}")
        if not isinstance(base_channels, int) or base_channels <= 0:
            raise MSSFError(f"base_channels: expected a positive int, got {base_channels!r}")
        out_indices = tuple(out_indices)
        if not out_indices or any(i not in (0, 1, 2, 3) for i in out_indices) or list(out_indices) != sorted(set(out_indices)):
            raise MSSFError(f"out_indices: expected increasing stage indices in 0..3, got {out_indices!r}")
        if not isinstance(frozen_stages, int) or not -1 <= frozen_stages <= 4:
            raise MSSFError(f"frozen_stages: expected an int in [-1, 4], got {frozen_stages!r}")
        block = BasicBlock if depth < 50 else Bottleneck
        self.depth, self.out_indices, self.frozen_stages, self.norm_eval = depth, out_indices, frozen_stages, norm_eval
        self.conv1 = nn.Conv2d(3, base_channels, 7, 2, 3, bias=False)
        self.bn1 = norm_layer(base_channels)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        in_ch = base_channels
        self.out_channels: List[int] = []
        for i, n in enumerate(RESNET_LAYERS[depth]):
            ch = base_channels * 2**i
            layers = []
            for j in range(n):
                layers.append(block(in_ch, ch, stride=(1 if i == 0 or j > 0 else 2), norm_layer=norm_layer))
                in_ch = ch * block.expansion
            setattr(self, f"layer{i + 1}", nn.Sequential(*layers))
            self.out_channels.append(in_ch)
        self._freeze()

    def _frozen_modules(self) -> List[nn.Module]:
        mods: List[nn.Module] = []
        if self.frozen_stages >= 0:
            mods += [self.conv1, self.bn1]
        mods += [getattr(self, f"layer{i}") for i in range(1, self.frozen_stages + 1)]
        return mods

    def _freeze(self) -> None:
        for m in self._frozen_modules():
            for p in m.parameters():
                p.requires_grad_(False)

    def train(self, mode: bool = True) -> "ResNet":
        super().train(mode)
        if mode:
            # Frozen layers (and all BN layers under norm_eval) keep their running statistics.
            targets = [self] if self.norm_eval else self._frozen_modules()
            for t in targets:
                for m in t.modules():
                    if isinstance(m, nn.modules.batchnorm._BatchNorm):
                        m.eval()
        return self

    def forward(self, x: Tensor) -> List[Tensor]:
        check_shape(x, "x", (None, 3, None, None))
        x = self.maxpool(F.relu(self.bn1(self.conv1(x))))
        outs = []
        for i in range(4):
            x = getattr(self, f"layer{i + 1}")(x)
            if i in self.out_indices:
                outs.append(x)
        return outs


class _ConvModule(nn.Module):
    """A conv under the attribute name ``conv`` (mmdet's ConvModule layout without norm/act)."""

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv(x)


class FPN(nn.Module):
    """Feature pyramid: 1x1 laterals, nearest-neighbour top-down sums, 3x3 output convs.

    Args:
        in_channels: channels of every input level (fine to coarse).
        out_channels: channels of every output level.
        num_outs: number of outputs; extra levels (beyond the inputs) are max-pooled (kernel 1,
            stride 2) from the last output, as mmdet's FPN without extra convs.

    Shapes:
        - list of ``(B, C_i, H_i, W_i)`` -> list of ``num_outs`` ``(B, out_channels, H_l, W_l)``.
    """

    def __init__(self, in_channels: Sequence[int], out_channels: int = 256, num_outs: int = 4) -> None:
        super().__init__()
        in_channels = list(in_channels)
        if not in_channels or num_outs < len(in_channels):
            raise MSSFError(
                f"num_outs: expected >= len(in_channels) = {len(in_channels)} and at least one input level, got {num_outs}"
            )
        self.in_channels, self.out_channels, self.num_outs = in_channels, out_channels, num_outs
        self.lateral_convs = nn.ModuleList(_ConvModule(c, out_channels, 1) for c in in_channels)
        self.fpn_convs = nn.ModuleList(_ConvModule(out_channels, out_channels, 3) for _ in in_channels)

    def forward(self, inputs: Sequence[Tensor]) -> List[Tensor]:
        if len(inputs) != len(self.in_channels):
            raise MSSFError(f"inputs: expected {len(self.in_channels)} levels, got {len(inputs)}")
        lat = [conv(x) for conv, x in zip(self.lateral_convs, inputs)]
        for i in range(len(lat) - 1, 0, -1):
            lat[i - 1] = lat[i - 1] + F.interpolate(lat[i], size=lat[i - 1].shape[-2:], mode="nearest")
        outs = [conv(x) for conv, x in zip(self.fpn_convs, lat)]
        while len(outs) < self.num_outs:
            outs.append(F.max_pool2d(outs[-1], 1, stride=2))
        return outs


class ImageBranch(nn.Module):
    """ResNet + FPN over every camera of a batch.

    Args:
        depth, base_channels, out_indices, frozen_stages, norm_eval: see :class:`ResNet`.
        fpn_channels: FPN output channels.
        num_outs: FPN output levels.
        frozen: freeze the whole branch (paper: the image branch is pre-trained and frozen); the
            forward then runs without autograd and every BatchNorm stays in eval mode.
        channels_last: run the convolutions on channels-last memory and return channels-last levels
            (the default; the same values up to rounding as ``False``, the NCHW layout; ``stride(2) ==
            1``). MSDFF then reads every pixel's channels as one contiguous row (its ``direct`` plan)
            instead of gathering them from 256 channel planes, which costs it about twice as much
            (``docs/performance.md``); PyTorch's CPU convolutions are as fast or faster in this layout
            (ResNet-50 + FPN on a 608 x 968 image: 1.53 s against 1.58 s, one core). Converting NCHW
            levels afterwards costs about as much as it saves (130 ms for VoD's four 256-channel
            levels against 100-130 ms for two MSDFF blocks, one core).

    Shapes:
        - images ``(B, V, 3, H, W)`` -> list of ``num_outs`` levels ``(B, V, fpn_channels, H_l, W_l)``
          with ``H_l = ceil(H / (4 * 2**l))`` for inputs divisible by 32.
    """

    def __init__(
        self,
        depth: int = 50,
        base_channels: int = 64,
        fpn_channels: int = 256,
        num_outs: int = 4,
        out_indices: Sequence[int] = (0, 1, 2, 3),
        frozen: bool = False,
        frozen_stages: int = -1,
        norm_eval: bool = False,
        channels_last: bool = True,
    ) -> None:
        super().__init__()
        self.backbone = ResNet(depth, base_channels, out_indices, frozen_stages, norm_eval)
        self.channels_last = bool(channels_last)
        self.neck = FPN([self.backbone.out_channels[i] for i in out_indices], fpn_channels, num_outs)
        self.frozen = bool(frozen)
        if self.frozen:
            for p in self.parameters():
                p.requires_grad_(False)

    @property
    def out_channels(self) -> int:
        return self.neck.out_channels

    def train(self, mode: bool = True) -> "ImageBranch":
        super().train(mode and not self.frozen)
        return self

    def forward(self, images: Tensor) -> List[Tensor]:
        check_shape(images, "images", (None, None, 3, None, None))
        check_floating(images, "images")
        b, v = images.shape[:2]
        x = images.flatten(0, 1)
        if self.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.frozen):
            feats = self.neck(self.backbone(x))
        if self.channels_last:  # (convolutions keep the format; make sure of every level, e.g. after upsampling)
            feats = [f.contiguous(memory_format=torch.channels_last) for f in feats]
        return [f.unflatten(0, (b, v)) for f in feats]

    @staticmethod
    def level_strides(num_outs: int = 4) -> Tuple[int, ...]:
        """Stride of every output level relative to the input image."""
        return tuple(4 * 2**i for i in range(num_outs))
