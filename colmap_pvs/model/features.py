"""Shared 2D feature extraction (paper sec. 3.1) with FPN-style finer outputs for the cascade."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .layers import Conv, ConvBnReLU


class FeatureNet(nn.Module):
    """2D CNN shared by all views.

    Input ``[B, 3, H, W]`` (``H, W`` divisible by 4); outputs, coarse to fine,
    ``[B, F0, H/4, W/4]``, ``[B, F1, H/2, W/2]``, ``[B, F2, H, W]`` with
    ``(F0, F1, F2) = channels``. Only the first ``levels`` outputs are computed.
    """

    def __init__(self, channels: tuple[int, ...] = (32, 16, 8)) -> None:
        super().__init__()
        c0, c1, c2 = 8, 16, 32  # encoder widths at H, H/2, H/4
        f0, f1, f2 = channels
        self.enc0 = ConvBnReLU(3, c0, dims=2)
        self.enc1 = nn.Sequential(
            ConvBnReLU(c0, c1, dims=2, kernel=5, stride=2),
            ConvBnReLU(c1, c1, dims=2),
            ConvBnReLU(c1, c1, dims=2),
        )
        self.enc2 = nn.Sequential(
            ConvBnReLU(c1, c2, dims=2, kernel=5, stride=2),
            ConvBnReLU(c2, c2, dims=2),
            ConvBnReLU(c2, c2, dims=2),
        )
        self.out0 = Conv(c2, f0, dims=2, kernel=1)
        # Top-down pathway: reduce, upsample x2 (nearest), add the lateral, smooth.
        self.top1 = Conv(c2, c1, dims=2, kernel=1)
        self.lat1 = Conv(c1, c1, dims=2, kernel=1)
        self.out1 = Conv(c1, f1, dims=2, kernel=3)
        self.top2 = Conv(c1, c0, dims=2, kernel=1)
        self.lat2 = Conv(c0, c0, dims=2, kernel=1)
        self.out2 = Conv(c0, f2, dims=2, kernel=3)

    def forward(self, x: torch.Tensor, levels: int = 3) -> list[torch.Tensor]:
        if torch.is_grad_enabled() or x.shape[0] == 1:
            return self._forward(x, levels)
        # Inference: one image at a time (the full-resolution temporaries of one image only),
        # written into the channels-last outputs.
        outs: list[torch.Tensor] = []
        for i in range(x.shape[0]):
            one = self._forward(x[i : i + 1], levels)
            if not outs:
                shape = lambda t: (x.shape[0], *t.shape[1:])  # noqa: E731
                outs = [
                    torch.empty(shape(t), dtype=t.dtype, device=t.device, memory_format=torch.channels_last)
                    for t in one
                ]
            for buf, t in zip(outs, one, strict=True):
                buf[i : i + 1].copy_(t)
        return outs

    def _forward(self, x: torch.Tensor, levels: int) -> list[torch.Tensor]:
        x = x.contiguous(memory_format=torch.channels_last)
        e0 = self.enc0(x)
        e1 = self.enc1(e0)
        e2 = self.enc2(e1)
        outs = [self.out0(e2)]
        if levels >= 2:
            inner1 = F.interpolate(self.top1(e2), scale_factor=2.0, mode="nearest") + self.lat1(e1)
            outs.append(self.out1(inner1))
            if levels >= 3:
                inner2 = F.interpolate(self.top2(inner1), scale_factor=2.0, mode="nearest") + self.lat2(e0)
                outs.append(self.out2(inner2))
        return outs
