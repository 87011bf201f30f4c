"""3D cost-volume filtering networks (paper sec. 3.3): a 3D ResNet and stacked 3-scale 3D U-Nets.

All volumes are ``[B, C, D, h, w]`` with ``D``, ``h`` and ``w`` divisible by 4.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .layers import Conv, ConvBnReLU, Up3d


class UNet3D(nn.Module):
    """Three-scale 3D U-Net: ``[B, cin, D, h, w] -> [B, c, D, h, w]`` features (widths ``c, 2c, 4c``).

    Every layer is Conv3d + BN + ReLU; the decoder upsamples with a 1x1x1 Conv3d+BN+ReLU
    followed by trilinear x2 interpolation and adds the skip connection. ``D, h, w`` must be
    divisible by 4.
    """

    def __init__(self, cin: int, c: int) -> None:
        super().__init__()
        self.conv0 = ConvBnReLU(cin, c)
        self.down1 = ConvBnReLU(c, 2 * c, stride=2)
        self.conv1 = ConvBnReLU(2 * c, 2 * c)
        self.down2 = ConvBnReLU(2 * c, 4 * c, stride=2)
        self.conv2 = ConvBnReLU(4 * c, 4 * c)
        self.up1 = Up3d(4 * c, 2 * c)
        self.up0 = Up3d(2 * c, c)
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x0 = self.conv0(x)
        x1 = self.conv1(self.down1(x0))
        x2 = self.conv2(self.down2(x1))
        y1 = self.up1.add_to(x2, x1)
        del x1, x2
        return self.up0.add_to(y1, x0)


class ResNet3D(nn.Module):
    """3D ResNet: ``[B, cin, D, h, w] -> [B, c, D, h, w]`` (an input layer and ``blocks`` residual blocks)."""

    def __init__(self, cin: int, c: int, blocks: int) -> None:
        super().__init__()
        self.inp = ConvBnReLU(cin, c)
        self.blocks = nn.ModuleList(
            nn.ModuleList([ConvBnReLU(c, c), ConvBnReLU(c, c, relu=False)]) for _ in range(blocks)
        )
        self.out_channels = c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.inp(x)
        for a, b in self.blocks:
            x = F.relu(b(a(x)) + x) if torch.is_grad_enabled() else b(a(x)).add_(x).relu_()
        return x


class CoarseRegularizer(nn.Module):
    """Coarse-stage filtering: a 3D ResNet then two stacked 3D U-Nets (stacked-hourglass style).

    ``[B, G, D, h, w]`` aggregated cost -> three ``[B, D, h, w]`` logit volumes (softmax over
    ``D`` gives the three probability volumes), from the ResNet, U-Net 1 and U-Net 2.
    U-Net ``k`` refines the previous features residually.
    """

    def __init__(self, cin: int, c: int, resnet_blocks: int) -> None:
        super().__init__()
        self.resnet = ResNet3D(cin, c, resnet_blocks)
        self.unet1 = UNet3D(c, c)
        self.unet2 = UNet3D(c, c)
        self.head0 = Conv(c, 1)
        self.head1 = Conv(c, 1)
        self.head2 = Conv(c, 1)

    def forward(self, cost: torch.Tensor) -> list[torch.Tensor]:
        f0 = self.resnet(cost)
        logits = [self.head0(f0).squeeze(1)]
        f1 = _add(self.unet1(f0), f0)
        logits.append(self.head1(f1).squeeze(1))
        del f0
        f2 = _add(self.unet2(f1), f1)
        del f1
        logits.append(self.head2(f2).squeeze(1))
        return logits


class StageRegularizer(nn.Module):
    """Cascade-stage filtering: a 3D U-Net and a 1x1x1 1-channel head, ``[B, G, D, h, w] -> [B, D, h, w]``.

    The cheap 1x1x1 head (instead of 3x3x3) saves ~15% of a full-resolution forward pass on CPU.
    """

    def __init__(self, cin: int, c: int) -> None:
        super().__init__()
        self.unet = UNet3D(cin, c)
        self.head = Conv(c, 1, kernel=1)

    def forward(self, cost: torch.Tensor) -> torch.Tensor:
        return self.head(self.unet(cost)).squeeze(1)


def _add(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``y + x``; in place into ``y`` (a fresh network output) without autograd."""
    return y + x if torch.is_grad_enabled() else y.add_(x)
