"""The density networks: the default C-CNN-style net (about 60 k parameters), the cheaper
:class:`SLZFastNet` (version 3, beside the default) and the large teacher used in distillation.

Input: ``(N, 3, H, W)`` BGR scaled to [0, 1] then ``(x - 0.45) / 0.25``; H and W multiples of 4.
Output: ``(N, 1, H/4, W/4)`` logits during training; the exported model ends in a sigmoid, so the
shipped map is the probability, per 4x4-pixel cell, that a person is there (an occupancy score,
not a count: see ``companion/models/MODEL_CARD.md``).

Layout (C-CNN of Shi et al. 2020 in spirit): three parallel stride-2 branches with 9x9, 7x7 and
5x5 kernels see people of different sizes at full input resolution (tiny people from above need
it), a 2x2 max-pool, then four 3x3 convolutions, two of them dilated for context. Every network
here keeps that contract (input, stride-4 output), so the runner and the calibration take any.
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


class SLZFastNet(nn.Module):
    """A cheaper student with the same contract as :class:`SLZDensityNet` (issue 13's 20 ms frame).

    The C-CNN stem's three wide kernels on the full-resolution frame cost 0.44 GMAC at 640x480,
    and its body of 40-channel 3x3 convolutions at stride 4 another 1.05 G. Here two strided 3x3
    convolutions take the frame to stride 4 (3 -> ``stem`` -> ``width`` channels: 0.1-0.2 GMAC)
    and the body is ``width`` wide; with ``depthwise`` each body layer is a depthwise 3x3 plus a
    pointwise 1x1 (MobileNet style), a seventh of the multiply-adds. Dilations 1, 2, 3, 1 (and a
    fifth layer, dilation 2, for the depthwise body) keep the receptive field near the C-CNN's.
    """

    def __init__(self, width: int = 32, stem: int = 24, depthwise: bool = False) -> None:
        super().__init__()
        self.stem = nn.Sequential(_cbr(3, stem, 3, 2), _cbr(stem, width, 3, 2))
        if depthwise:
            self.body = nn.Sequential(*(_dws(width, width, d) for d in (1, 2, 3, 1, 2)))
            last = width
        else:
            self.body = nn.Sequential(_cbr(width, width, 3), _cbr(width, width, 3, dilation=2),
                                      _cbr(width, width, 3, dilation=3), _cbr(width, 32, 3))
            last = 32
        self.head = nn.Conv2d(last, 1, 1)
        assert self.head.bias is not None
        nn.init.constant_(self.head.bias, -4.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(self.stem(x)))


def _dws(cin: int, cout: int, dilation: int) -> nn.Sequential:
    """Depthwise 3x3 (dilated) then pointwise 1x1, each with BN and ReLU (folded on export)."""
    dw = nn.Sequential(nn.Conv2d(cin, cin, 3, 1, dilation, dilation=dilation, groups=cin, bias=False),
                       nn.BatchNorm2d(cin), nn.ReLU(inplace=True))
    return nn.Sequential(dw, _cbr(cin, cout, 1))


def student(arch: str, width: int) -> nn.Module:
    """A student network by architecture letter: ``""`` the C-CNN (:class:`SLZDensityNet`), ``"f"``
    :class:`SLZFastNet`, ``"l"`` :class:`SLZFastNet` with the depthwise ("lite") body."""
    if arch == "":
        return SLZDensityNet(width)
    if arch in ("f", "l"):
        return SLZFastNet(width, depthwise=arch == "l")
    raise ValueError(f"unknown student architecture {arch!r} (known: '', 'f', 'l')")


def load_folded_onnx(net: nn.Module, path: str) -> int:
    """Start ``net`` from an exported model's weights (batch norm was folded into them on export).

    The ONNX file's Conv nodes, in graph order, must match ``net``'s Conv2d modules in
    registration order (true of every network here: both follow ``forward``). Each convolution
    takes the folded weight; the batch norm after it becomes the identity on those weights (scale
    1, mean 0, variance 1 - eps) with the folded bias as its shift, so ``net`` in eval mode computes
    the file's map. Fine-tune with the batch norms in eval mode (:func:`freeze_batchnorm`): in train
    mode they would normalise by batch statistics and the start would be lost. Returns the number of
    convolutions loaded; ValueError when the file does not fit ``net``.
    """
    import onnx
    from onnx import numpy_helper

    try:
        proto = onnx.load(path)
    except Exception as exc:  # onnx raises protobuf's DecodeError, OSError, ...
        raise ValueError(f"{path}: not a readable ONNX model ({exc})") from None
    inits = {t.name: numpy_helper.to_array(t) for t in proto.graph.initializer}
    for node in proto.graph.node:  # the exporter shares equal tensors through Identity or Constant nodes
        if node.op_type == "Identity" and node.input[0] in inits:
            inits[node.output[0]] = inits[node.input[0]]
        elif node.op_type == "Constant" and node.attribute and node.attribute[0].name == "value":
            inits[node.output[0]] = numpy_helper.to_array(node.attribute[0].t)
    convs = [n for n in proto.graph.node if n.op_type == "Conv"]
    mods = [m for m in net.modules() if isinstance(m, nn.Conv2d)]
    if len(convs) != len(mods):
        raise ValueError(f"{path}: {len(convs)} convolutions, the network has {len(mods)}")
    bn_after = {}
    for seq in net.modules():
        if isinstance(seq, nn.Sequential) and len(seq) >= 2 and isinstance(seq[0], nn.Conv2d) \
                and isinstance(seq[1], nn.BatchNorm2d):
            bn_after[id(seq[0])] = seq[1]
    with torch.no_grad():
        for node, conv in zip(convs, mods):
            if len(node.input) < 2 or any(name not in inits for name in node.input[1:]):
                raise ValueError(f"{path}: convolution {node.name!r} has no constant weight or bias")
            w = torch.from_numpy(inits[node.input[1]].copy())
            b = torch.from_numpy(inits[node.input[2]].copy()) if len(node.input) > 2 else torch.zeros(w.shape[0])
            if tuple(w.shape) != tuple(conv.weight.shape):
                raise ValueError(f"{path}: convolution {node.name!r} is {tuple(w.shape)}, "
                                 f"the network's is {tuple(conv.weight.shape)}")
            conv.weight.copy_(w)
            bn = bn_after.get(id(conv))
            if bn is not None:
                bn.weight.fill_(1.0)
                bn.bias.copy_(b)
                mean, var = bn.running_mean, bn.running_var
                assert mean is not None and var is not None  # track_running_stats is on
                mean.zero_()
                var.fill_(1.0 - bn.eps)
            elif conv.bias is not None:
                conv.bias.copy_(b)
            elif bool(b.abs().max() > 0):
                raise ValueError(f"{path}: convolution {node.name!r} has a bias the network cannot hold")
    return len(mods)


def freeze_batchnorm(net: nn.Module) -> None:
    """Batch norms to eval mode (running statistics, still learnable scale and shift); call after
    ``net.train()``."""
    for m in net.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()


class Exported(nn.Module):
    """The deployable form: batch norm folded into the convolutions, sigmoid at the end."""

    def __init__(self, net: nn.Module) -> None:
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
