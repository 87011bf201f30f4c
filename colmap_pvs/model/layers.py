"""Convolution building blocks tuned for CPU inference and training.

PyTorch routes a float32 CPU convolution to oneDNN (fast) or to its native im2col
kernels (often 5-30x slower for the thin 3D cost volumes used here) by a size
heuristic: oneDNN is used when ``groups > 1`` or ``batch > 1`` or
``B * C * D * H > 20480``. For a small input with batch 1 we therefore compute the
*same* dense convolution as a 2-group convolution of the input concatenated with
itself (group ``g`` produces output channels ``g * Cout/2 ...``), which oneDNN runs in
forward and backward. The result is numerically the same dense convolution.

In eval mode the batch norms are folded into the convolution weights on the fly.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

_NATIVE_LIMIT = 20480  # PyTorch's "native is faster" threshold on B*C*D*H (ConvUtils.h)


def _needs_group_trick(x: torch.Tensor) -> bool:
    return (
        x.device.type == "cpu"
        and x.dtype == torch.float32
        and x.shape[0] == 1
        and x.shape[0] * x.shape[1] * x.shape[2] * x.shape[3] <= _NATIVE_LIMIT
        and torch.backends.mkldnn.is_available()
    )


def conv_nd(
    x: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    stride: int = 1,
    padding: int = 1,
) -> torch.Tensor:
    """Dense 2D/3D convolution (``weight`` ``[Cout, Cin, k...]``) that always takes the oneDNN path on CPU."""
    conv = F.conv3d if x.dim() == 5 else F.conv2d
    if not _needs_group_trick(x):
        return conv(x, weight, bias, stride, padding)
    cout = weight.shape[0]
    if cout % 2:
        weight = torch.cat([weight, torch.zeros_like(weight[:1])], 0)
        if bias is not None:
            bias = torch.cat([bias, torch.zeros_like(bias[:1])], 0)
    y = conv(torch.cat([x, x], 1), weight, bias, stride, padding, 1, 2)
    return y[:, :cout] if cout % 2 else y


def conv_transpose3d(
    x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int = 2
) -> torch.Tensor:
    """``k=3, padding=1, output_padding=stride-1`` transposed 3D convolution (doubles each axis for stride 2).

    ``weight`` is ``[Cin, Cout, 3, 3, 3]``; ``Cout`` must be even when the group trick applies.
    """
    if not _needs_group_trick(x) or weight.shape[1] % 2:
        return F.conv_transpose3d(x, weight, bias, stride, 1, stride - 1)
    half = weight.shape[1] // 2
    w2 = torch.cat([weight[:, :half], weight[:, half:]], 0)
    return F.conv_transpose3d(torch.cat([x, x], 1), w2, bias, stride, 1, stride - 1, 2)


class ConvBnReLU(nn.Module):
    """Conv (2D or 3D, kernel k, no bias) + BatchNorm + optional ReLU.

    ``[B, Cin, *S] -> [B, Cout, *S/stride]`` (``*S*stride`` when ``transposed``).
    """

    def __init__(
        self,
        cin: int,
        cout: int,
        *,
        dims: int = 3,
        kernel: int = 3,
        stride: int = 1,
        relu: bool = True,
        transposed: bool = False,
    ) -> None:
        super().__init__()
        if transposed and (dims != 3 or kernel != 3):
            raise ValueError("transposed ConvBnReLU supports 3D kernel 3 only")
        self.stride = stride
        self.padding = kernel // 2
        self.relu = relu
        self.transposed = transposed
        shape = (cin, cout) if transposed else (cout, cin)
        self.weight = nn.Parameter(torch.empty(*shape, *([kernel] * dims)))
        nn.init.kaiming_uniform_(self.weight, a=5**0.5)
        self.bn = nn.BatchNorm3d(cout) if dims == 3 else nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training or not self.bn.track_running_stats or self.bn.running_var is None:
            y = self._conv(x, self.weight, None)
            y = self.bn(y)
            return F.relu(y) if self.relu else y
        # Eval: fold the batch norm into the convolution.
        bn = self.bn
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        bias = bn.bias - bn.running_mean * scale
        shape = [1, -1] if self.transposed else [-1, 1]
        w = self.weight * scale.view(*shape, *([1] * (self.weight.dim() - 2)))
        y = self._conv(x, w, bias)
        return F.relu_(y) if self.relu else y

    def _conv(self, x: torch.Tensor, w: torch.Tensor, b: torch.Tensor | None) -> torch.Tensor:
        if self.transposed:
            return conv_transpose3d(x, w, b, self.stride)
        return conv_nd(x, w, b, self.stride, self.padding)


class Conv(nn.Module):
    """Plain 2D/3D convolution with bias (used for 1-channel output heads)."""

    def __init__(self, cin: int, cout: int, *, dims: int = 3, kernel: int = 3) -> None:
        super().__init__()
        self.padding = kernel // 2
        self.weight = nn.Parameter(torch.empty(cout, cin, *([kernel] * dims)))
        self.bias = nn.Parameter(torch.zeros(cout))
        nn.init.kaiming_uniform_(self.weight, a=5**0.5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return conv_nd(x, self.weight, self.bias, 1, self.padding)


def to_volume_format(x: torch.Tensor, channels_last: bool) -> torch.Tensor:
    """``[B, C, D, H, W]`` in ``channels_last_3d`` memory format when requested (a no-op if it already is)."""
    if channels_last and x.dim() == 5:
        return x.contiguous(memory_format=torch.channels_last_3d)
    return x
