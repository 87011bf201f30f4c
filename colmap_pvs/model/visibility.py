"""Pixelwise visibility network and visibility-weighted cost aggregation (paper sec. 3.2).

For each source view ``i`` a 3D U-Net (weights shared across views) maps the two-view
cost volume ``C_i`` ``[B, G, D, h, w]`` to ``P_v = sigmoid(...)`` ``[B, D, h, w]``; the
visibility map is ``V_i = max_d P_v`` ``[B, 1, h, w]``; truncation keeps ``V_i' = V_i``
where ``V_i > tau`` and 0 elsewhere; the aggregated volume is
``C = sum_i V_i' C_i / sum_i V_i'``, with the plain mean of the ``C_i`` where every
view was truncated.
"""

from __future__ import annotations

import torch
from torch import nn

from .layers import Conv
from .regularization import UNet3D
from .runtime import exporting

#: Below this total visibility weight a pixel falls back to the plain mean.
WEIGHT_EPS = 1e-6


class VisibilityNet(nn.Module):
    """``[B, G, D, h, w]`` two-view cost -> visibility map ``V = max_d P_v`` ``[B, 1, h, w]`` in ``(0, 1)``.

    A 3-scale 3D U-Net (Conv3d+BN+ReLU layers) followed by a 1-channel 1x1x1 Conv3d and a sigmoid.
    """

    def __init__(self, groups: int, c: int) -> None:
        super().__init__()
        self.unet = UNet3D(groups, c)
        self.head = Conv(c, 1, kernel=1)

    def probability(self, cost: torch.Tensor) -> torch.Tensor:
        """The per-hypothesis visibility probability ``P_v`` ``[B, D, h, w]``."""
        return torch.sigmoid(self.head(self.unet(cost)).squeeze(1))

    def forward(self, cost: torch.Tensor) -> torch.Tensor:
        # max commutes with the monotonic sigmoid: take the max over depth of the logits first.
        logits = self.head(self.unet(cost))  # [B, 1, D, h, w]
        return torch.sigmoid(logits.amax(2))


def truncate_visibility(vis: torch.Tensor, tau: float) -> torch.Tensor:
    """``V' = V`` where ``V > tau``, else 0 (any shape; differentiable where kept)."""
    return torch.where(vis > tau, vis, torch.zeros_like(vis))


def normalized_weights(weights: list[torch.Tensor]) -> list[torch.Tensor]:
    """``w_i / sum_j w_j`` for ``[B, 1, h, w]`` maps, ``1 / n`` where ``sum_j w_j <= WEIGHT_EPS``."""
    total = weights[0]
    for w in weights[1:]:
        total = total + w
    ok = total > WEIGHT_EPS
    uniform = torch.full_like(total, 1.0 / len(weights))
    inv = 1.0 / total.clamp_min(WEIGHT_EPS)
    return [torch.where(ok, w * inv, uniform) for w in weights]


class CostAccumulator:
    """Running weighted mean of cost volumes, one source at a time (memory independent of ``N``).

    ``add(cost [B, G, D, h, w], weight [B, 1, h, w], per plane [B, D, h, w], or None)``; ``result()`` returns
    ``sum_i w_i C_i / sum_i w_i`` where ``sum_i w_i > WEIGHT_EPS`` and the plain mean of
    the ``C_i`` elsewhere (all views truncated). With ``weight=None`` for every view it is
    the plain mean. Without autograd the accumulation is in place (``cost`` may be reused
    as a buffer).
    """

    def __init__(self) -> None:
        self.weighted: torch.Tensor | None = None
        self.plain: torch.Tensor | None = None
        self.weight_sum: torch.Tensor | None = None
        self.count = 0

    def add(self, cost: torch.Tensor, weight: torch.Tensor | None) -> None:
        inplace = not torch.is_grad_enabled()
        self.count += 1
        if weight is not None:
            w = weight.unsqueeze(1)  # [B, 1, 1, h, w]
            if self.weighted is None:
                self.weighted, self.weight_sum = cost * w, weight
            else:
                self.weighted = (
                    self.weighted.addcmul_(cost, w) if inplace else torch.addcmul(self.weighted, cost, w)
                )
                self.weight_sum = self.weight_sum + weight
        if self.plain is None:
            self.plain = cost
        else:
            self.plain = self.plain.add_(cost) if inplace else self.plain + cost

    def result(self) -> torch.Tensor:
        if self.count == 0 or self.plain is None:
            raise ValueError("CostAccumulator: no cost volume was added")
        if self.weighted is None:
            return self.plain.div_(self.count) if not torch.is_grad_enabled() else self.plain / self.count
        ws = self.weight_sum.unsqueeze(1)
        ok = ws > WEIGHT_EPS
        mean = self.weighted / ws.clamp_min(WEIGHT_EPS)
        if not exporting() and bool(ok.all()):  # torch.where gives the same values
            return mean
        return torch.where(ok, mean, self.plain / self.count)


def aggregate(costs: list[torch.Tensor], weights: list[torch.Tensor] | None) -> torch.Tensor:
    """Visibility-weighted mean of ``costs`` (each ``[B, G, D, h, w]``) with ``weights`` ``[B, 1, h, w]``.

    ``weights=None`` gives the plain mean. See :class:`CostAccumulator`.
    """
    acc = CostAccumulator()
    for i, c in enumerate(costs):
        acc.add(c, None if weights is None else weights[i])
    return acc.result()
