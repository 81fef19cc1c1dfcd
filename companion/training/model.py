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
