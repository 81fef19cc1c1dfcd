"""The shipped density network: a compact C-CNN-style net (about 60 k parameters).

Input: ``(N, 3, H, W)`` BGR scaled to [0, 1] then ``(x - 0.45) / 0.25``; H and W multiples of 4.
Output: ``(N, 1, H/4, W/4)`` logits during training; the exported model ends in a sigmoid, so the
shipped map is the probability, per 4x4-pixel cell, that a person is there (an occupancy score,
not a count: see ``companion/models/MODEL_CARD.md``).

Layout (C-CNN of Shi et al. 2020 in spirit): three parallel stride-2 branches with 9x9, 7x7 and
5x5 kernels see people of different sizes at full input resolution (tiny people from above need
it), a 2x2 max-pool, then four 3x3 convolutions, two of them dilated for context.
"""

from __future__ import annotations

from typing import TypeVar

import torch
from torch import nn

COLOR = "bgr"
SCALE = 1.0 / 255.0
MEAN = (0.45, 0.45, 0.45)
STD = (0.25, 0.25, 0.25)
STRIDE = 4

NetT = TypeVar("NetT", bound=nn.Module)


def _cbr(cin: int, cout: int, k: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    pad = dilation * (k - 1) // 2
    return nn.Sequential(
        nn.Conv2d(cin, cout, k, stride, pad, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class SLZDensityNet(nn.Module):
    def __init__(self, width: int = 40) -> None:
        super().__init__()
        self.b9 = _cbr(3, 10, 9, 2)
        self.b7 = _cbr(3, 14, 7, 2)
        self.b5 = _cbr(3, 16, 5, 2)
        self.pool = nn.MaxPool2d(2)
        self.body = nn.Sequential(
            _cbr(40, width, 3),
            _cbr(width, width, 3, dilation=2),
            _cbr(width, width, 3, dilation=3),
            _cbr(width, 32, 3),
        )
        self.head = nn.Conv2d(32, 1, 1)
        assert self.head.bias is not None  # Conv2d has a bias by default
        nn.init.constant_(self.head.bias, -4.0)  # start near "nobody": most pixels are empty

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.cat([self.b9(x), self.b7(x), self.b5(x)], dim=1)
        return self.head(self.body(self.pool(x)))


class Exported(nn.Module):
    """The deployable form: batch norm folded into the convolutions, sigmoid at the end."""

    def __init__(self, net: SLZDensityNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(x))


def fold_batchnorm(net: NetT) -> NetT:
    """A copy of ``net`` (eval mode) with every Conv+BN pair fused into one convolution."""
    import copy

    from torch.nn.utils.fusion import fuse_conv_bn_eval

    net = copy.deepcopy(net).eval()
    for mod in net.modules():
        if isinstance(mod, nn.Sequential) and len(mod) == 3 and isinstance(mod[1], nn.BatchNorm2d):
            conv = mod[0]
            assert isinstance(conv, nn.Conv2d)
            mod[0] = fuse_conv_bn_eval(conv, mod[1])
            mod[1] = nn.Identity()
    return net


def count_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


class _Res(nn.Module):
    """Two 3x3 conv-BN layers with an identity shortcut."""

    def __init__(self, c: int, dilation: int = 1) -> None:
        super().__init__()
        self.a = _cbr(c, c, 3, dilation=dilation)
        self.b = nn.Sequential(nn.Conv2d(c, c, 3, 1, dilation, dilation=dilation, bias=False), nn.BatchNorm2d(c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x + self.b(self.a(x)))


class TeacherNet(nn.Module):
    """The large teacher for distillation (about 5.6 M parameters; trained on a GPU, never shipped).

    Same input and output contract as :class:`SLZDensityNet` (normalised BGR in, stride-4 logits
    out) so a student learns its map cell for cell. A small U-Net: full-resolution 3x3 stem, residual
    stages at strides 4, 8 and 16 (the last dilated, a receptive field of a few hundred pixels, to
    tell a person from a roof vent by what surrounds it), then back up to stride 4 with skips.
    """

    def __init__(self, c: int = 64) -> None:
        super().__init__()
        self.stem = nn.Sequential(_cbr(3, 32, 3), _cbr(32, 48, 3, 2), _cbr(48, c, 3, 2), _Res(c), _Res(c))
        self.down8 = nn.Sequential(_cbr(c, 2 * c, 3, 2), _Res(2 * c), _Res(2 * c), _Res(2 * c))
        self.down16 = nn.Sequential(_cbr(2 * c, 4 * c, 3, 2), _Res(4 * c), _Res(4 * c, 2), _Res(4 * c, 4))
        self.up8 = _cbr(4 * c + 2 * c, 2 * c, 3)
        self.up4 = nn.Sequential(_cbr(2 * c + c, c, 3), _Res(c))
        self.head = nn.Conv2d(c, 1, 1)
        assert self.head.bias is not None
        nn.init.constant_(self.head.bias, -4.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s4 = self.stem(x)
        s8 = self.down8(s4)
        s16 = self.down16(s8)
        u8 = self.up8(torch.cat([s8, nn.functional.interpolate(s16, size=s8.shape[-2:], mode="nearest")], 1))
        u4 = self.up4(torch.cat([s4, nn.functional.interpolate(u8, size=s4.shape[-2:], mode="nearest")], 1))
        return self.head(u4)
