"""Convolution building blocks tuned for CPU inference and training.

PyTorch routes a float32 CPU convolution to oneDNN (fast) or to its native im2col
kernels (several times slower for the thin 3D cost volumes used here) by a size
heuristic: oneDNN is used when ``groups > 1`` or ``batch > 1`` or
``B * C * D * H > 20480``. For a small input with batch 1 we therefore compute the
*same* dense convolution as a 2-group convolution of the input concatenated with
itself (group ``g`` produces output channels ``g * Cout/2 ...``), which oneDNN runs in
forward and backward. The result is numerically the same dense convolution.
Without autograd (``torch.no_grad``/``inference_mode``) the oneDNN convolution is
called directly, whatever the size.

In eval mode the batch norms are folded into the convolution weights on the fly.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from torch import nn

from .runtime import chunk_bytes, exporting

_NATIVE_LIMIT = 20480  # PyTorch's "native is faster" threshold on B*C*D*H (ConvUtils.h)


_HAS_MKLDNN_CONV = hasattr(torch, "mkldnn_convolution")


def _onednn_ok(x: torch.Tensor) -> bool:
    return x.device.type == "cpu" and x.dtype == torch.float32 and torch.backends.mkldnn.is_available()


@functools.cache
def _onednn_low_precision_ok(dtype: torch.dtype) -> bool:
    """Whether oneDNN has native ``dtype`` (bfloat16) convolutions on this CPU (else PyTorch's own
    kernels are used, slower but available everywhere)."""
    if not torch.backends.mkldnn.is_available():
        return False
    check = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    return dtype == torch.bfloat16 and check is not None and bool(check())


def _needs_group_trick(x: torch.Tensor) -> bool:
    return (
        x.shape[0] == 1
        and x.shape[0] * x.shape[1] * x.shape[2] * x.shape[3] <= _NATIVE_LIMIT
        and _onednn_ok(x)
    )


def conv_nd(
    x: torch.Tensor,
    weight: torch.Tensor,
    bias: torch.Tensor | None,
    stride: int = 1,
    padding: int = 1,
    compute_dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Dense 2D/3D convolution (``weight`` ``[Cout, Cin, k...]``) that always takes the oneDNN path on CPU.

    With ``compute_dtype`` (e.g. ``torch.bfloat16``) and no autograd, input, weight and bias are cast to it
    and the output has that dtype.
    """
    conv = F.conv3d if x.dim() == 5 else F.conv2d
    if exporting():  # the runtime picks its own kernels: the plain convolution, which every exporter maps
        return conv(x.to(weight.dtype), weight, bias, stride, padding)
    if compute_dtype is not None and not torch.is_grad_enabled() and x.is_floating_point():
        x, weight = x.to(compute_dtype), weight.to(compute_dtype)
        bias = None if bias is None else bias.to(compute_dtype)
        if x.device.type == "cpu" and _HAS_MKLDNN_CONV and _onednn_low_precision_ok(x.dtype):
            n = x.dim() - 2
            return torch.mkldnn_convolution(x, weight, bias, [padding] * n, [stride] * n, [1] * n, 1)
        return conv(x, weight, bias, stride, padding)
    if x.dtype != weight.dtype:  # a low-precision activation reaching a float32 layer
        x = x.to(weight.dtype)
    if not torch.is_grad_enabled() and _HAS_MKLDNN_CONV and _onednn_ok(x):
        n = x.dim() - 2
        return torch.mkldnn_convolution(x, weight, bias, [padding] * n, [stride] * n, [1] * n, 1)
    if not _needs_group_trick(x):
        return conv(x, weight, bias, stride, padding)
    cout = weight.shape[0]
    if cout % 2:
        weight = torch.cat([weight, torch.zeros_like(weight[:1])], 0)
        if bias is not None:
            bias = torch.cat([bias, torch.zeros_like(bias[:1])], 0)
    y = conv(torch.cat([x, x], 1), weight, bias, stride, padding, 1, 2)
    return y[:, :cout] if cout % 2 else y


class ConvBnReLU(nn.Module):
    """Conv (2D or 3D, kernel k, no bias) + BatchNorm + optional ReLU.

    ``[B, Cin, *S] -> [B, Cout, *S/stride]``.
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
    ) -> None:
        super().__init__()
        self.stride = stride
        self.padding = kernel // 2
        self.relu = relu
        self.weight = nn.Parameter(torch.empty(cout, cin, *([kernel] * dims)))
        nn.init.kaiming_uniform_(self.weight, a=5**0.5)
        self.bn = nn.BatchNorm3d(cout) if dims == 3 else nn.BatchNorm2d(cout)
        #: Inference dtype of the convolution and of its output (``None`` = the weights'), see
        #: :func:`set_compute_dtype`. Not a parameter, not saved.
        self.compute_dtype: torch.dtype | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training or not self.bn.track_running_stats or self.bn.running_var is None:
            y = conv_nd(x, self.weight, None, self.stride, self.padding)
            y = self.bn(y)
            return F.relu(y) if self.relu else y
        # Eval: fold the batch norm into the convolution.
        bn = self.bn
        scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
        bias = bn.bias - bn.running_mean * scale
        w = self.weight * scale.view(-1, *([1] * (self.weight.dim() - 1)))
        y = conv_nd(x, w, bias, self.stride, self.padding, self.compute_dtype)
        return F.relu_(y) if self.relu else y


class Up3d(nn.Module):
    """U-Net decoder step: 1x1x1 Conv3d + BN + ReLU at the coarse scale, then trilinear x2 upsampling.

    ``[B, Cin, D, h, w] -> [B, Cout, 2D, 2h, 2w]`` (``align_corners=False``: voxel centres stay at
    ``i + 0.5``). Used instead of a stride-2 transposed convolution, which is several times slower on CPU.
    """

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.proj = ConvBnReLU(cin, cout, kernel=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.interpolate(self.proj(x), scale_factor=2.0, mode="trilinear", align_corners=False)

    def add_to(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        """``self(x) + skip``; without autograd computed into ``skip`` in place, a few rows at a time."""
        if torch.is_grad_enabled():
            return self(x) + skip
        return upsample2_add_(self.proj(x), skip)


def upsample2_add_(x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``out += trilinear_x2(x)`` in place (``align_corners=False``), for ``x`` ``[B, C, D, h, w]`` and
    ``out`` ``[B, C, 2D, 2h, 2w]``; returns ``out``.

    Works on bands of rows: each band of input rows ``[a, b)`` is upsampled with one row of context on
    either side (what the interpolation reads; at the image border the band is clamped exactly like the
    full interpolation), and the rows ``[2a, 2b)`` are added into ``out``. The same numbers as one
    ``F.interpolate`` followed by an addition, without the full-size temporaries. A channels-last band of
    one batch entry on the CPU is upsampled as two overlapping halves stacked into a batch of 2
    (:func:`_half_windows`): torch's CPU kernel runs one channels-last batch entry on one core, so this
    keeps two cores busy; each output row still reads the same inputs with the same weights (the halves
    are integer row shifts), so the numbers are the same.
    """
    B, C, D, h, w = x.shape
    if out.shape != (B, C, 2 * D, 2 * h, 2 * w):
        raise ValueError(f"upsample2_add_: out {tuple(out.shape)} is not twice x {tuple(x.shape)}")
    fmt = _memory_format(x)
    split = B == 1 and fmt == torch.channels_last_3d and x.device.type == "cpu"
    row_bytes = B * C * 4 * D * w * x.element_size()  # one input row becomes 2 x (2D x 2w) outputs
    rows = max(1, min(h, chunk_bytes() // max(1, row_bytes) - 2))
    for a in range(0, h, rows):
        b = min(h, a + rows)
        lo, hi = max(0, a - 1), min(h, b + 1)
        if split and b - a >= 2:
            # pieces: (batch entries, window start, first kept row, end of kept rows), rows of x
            top, n, mid = _half_windows(lo, hi)
            band = torch.cat([x[:, :, :, top : top + n], x[:, :, :, hi - n : hi]])
            pieces = ((slice(0, 1), top, a, mid), (slice(1, 2), hi - n, mid, b))
        else:
            # A contiguous copy of the (small) input band: interpolation of a strided view is slower.
            band = x[:, :, :, lo:hi]
            pieces = ((slice(None), lo, a, b),)
        up = F.interpolate(band.contiguous(memory_format=fmt), scale_factor=2.0, mode="trilinear",
                           align_corners=False)
        for entries, start, first, end in pieces:
            off = 2 * (first - start)
            out[:, :, :, 2 * first : 2 * end].add_(up[entries, :, :, off : off + 2 * (end - first)])
        del up, band
    return out


def _half_windows(lo: int, hi: int) -> tuple[int, int, int]:
    """Split the input rows ``[lo, hi)`` (``hi - lo >= 3``, or 2 at an image border) into two windows of
    ``n`` rows each, ``[lo, lo + n)`` and ``[hi - n, hi)``, that overlap by at least two rows; returns
    ``(lo, n, mid)``: the first window's rows are kept below ``mid``, the second's from ``mid``, so every
    kept row has its neighbours (or the image border) inside its own window."""
    n = (hi - lo + 1) // 2 + 1
    return lo, n, lo + n - 1


class Conv(nn.Module):
    """Plain 2D/3D convolution with bias (used for 1-channel output heads)."""

    def __init__(self, cin: int, cout: int, *, dims: int = 3, kernel: int = 3) -> None:
        super().__init__()
        self.padding = kernel // 2
        self.weight = nn.Parameter(torch.empty(cout, cin, *([kernel] * dims)))
        self.bias = nn.Parameter(torch.zeros(cout))
        nn.init.kaiming_uniform_(self.weight, a=5**0.5)
        #: Inference dtype of the convolution (the output is cast back to the weights' dtype).
        self.compute_dtype: torch.dtype | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = conv_nd(x, self.weight, self.bias, 1, self.padding, self.compute_dtype)
        return y if y.dtype == self.weight.dtype else y.to(self.weight.dtype)


def set_compute_dtype(module: nn.Module, dtype: torch.dtype | None) -> None:
    """Set the inference convolution dtype of every :class:`ConvBnReLU` and :class:`Conv` in ``module``.

    Hidden activations (``ConvBnReLU`` outputs) then stay in ``dtype``; ``Conv`` layers (output heads,
    feature outputs) return the weights' dtype (float32). Autograd (training) ignores it.
    """
    for m in module.modules():
        if isinstance(m, (ConvBnReLU, Conv)):
            m.compute_dtype = dtype


def to_volume_format(x: torch.Tensor, channels_last: bool) -> torch.Tensor:
    """``[B, C, D, H, W]`` in ``channels_last_3d`` memory format when requested (a no-op if it already is)."""
    if channels_last and x.dim() == 5:
        return x.contiguous(memory_format=torch.channels_last_3d)
    return x


def _memory_format(x: torch.Tensor) -> torch.memory_format:
    cl = x.is_contiguous(memory_format=torch.channels_last_3d)
    return torch.channels_last_3d if cl else torch.contiguous_format
