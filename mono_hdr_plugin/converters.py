"""Colour converters of Mono-HDR-3D (docs/method.md) and their ablation twins.

L2H-CC mirrors the inverted imaging equation I_h = X * S(I_l) + Y, one small network per
colour channel; H2L-CC mirrors I_l = D(I_h) + B(I_h) and closes the loop. The plain MLPs
have the same width and input/output ranges but none of that structure (paper, Table 4).
"""

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class PerChannelLinear(nn.Module):
    """Independent Linear(in_features -> out_features) layers, one per colour channel.

    Channel-first layout: input [C, N, in_features] -> output [C, N, out_features]. One
    batched matrix product runs the three "1 -> 128 -> 1" networks of the official code.
    """

    def __init__(self, in_features: int, out_features: int, channels: int = 3):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's default initialisation
        self.weight = nn.Parameter(torch.empty(channels, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(channels, 1, out_features).uniform_(-bound, bound))

    def forward(self, x: Tensor) -> Tensor:
        return torch.baddbmm(self.bias, x, self.weight)


def channels_first(colors: Tensor) -> Tensor:
    """[..., 3] -> [3, N, 1], the layout PerChannelLinear works in."""
    return colors.reshape(-1, colors.shape[-1]).T.unsqueeze(-1)


def channels_last(values: Tensor, shape: torch.Size) -> Tensor:
    """[3, N] -> [..., 3] with the leading shape of the original colours."""
    return values.T.reshape(shape)


class L2HColorConverter(nn.Module):
    """L2H-CC: LDR colour [..., 3] in [0, 1] -> HDR colour [..., 3] >= 0, per channel.

    latent = ReLU(W x); X = ReLU(.), S = ReLU(.), Y = linear; out = Softplus(x + X * S + Y).
    The three heads share one [hidden -> 3] product (columns X, S, Y), the same maths as
    three Linear(hidden -> 1) layers at a third of the memory traffic.
    """

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.latent = PerChannelLinear(1, hidden)
        self.heads = PerChannelLinear(hidden, 3)

    def forward(self, ldr: Tensor) -> Tensor:
        x = channels_first(ldr)
        gain, saturation, noise = self.heads(F.relu(self.latent(x))).unbind(-1)
        hdr = F.softplus(x.squeeze(-1) + F.relu(gain) * F.relu(saturation) + noise)
        return channels_last(hdr, ldr.shape)


class H2LColorConverter(nn.Module):
    """H2L-CC: normalised HDR pixel [..., 3] -> LDR pixel [..., 3] in (0, 1).

    latent = ReLU(W x); D = ReLU(.), B = Tanh(.); out = Sigmoid(D + B).
    """

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.latent = nn.Linear(3, hidden)
        self.response = nn.Linear(hidden, 3)
        self.bias = nn.Linear(hidden, 3)

    def forward(self, hdr: Tensor) -> Tensor:
        latent = F.relu(self.latent(hdr))
        return torch.sigmoid(F.relu(self.response(latent)) + torch.tanh(self.bias(latent)))


class PlainL2H(nn.Module):
    """Ablation: a plain per-channel MLP (1 -> hidden -> 1, Softplus out), no imaging structure."""

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.hidden = PerChannelLinear(1, hidden)
        self.out = PerChannelLinear(hidden, 1)

    def forward(self, ldr: Tensor) -> Tensor:
        hdr = F.softplus(self.out(F.relu(self.hidden(channels_first(ldr)))))
        return channels_last(hdr.squeeze(-1), ldr.shape)


class PlainH2L(nn.Module):
    """Ablation: a plain MLP (3 -> hidden -> 3, Sigmoid out) in place of H2L-CC."""

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(3, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, hdr: Tensor) -> Tensor:
        return torch.sigmoid(self.net(hdr))


class PerChannelCRF(nn.Module):
    """Learned camera response per channel: log exposure [..., 3] -> LDR [..., 3] in (0, 1).

    The tone mapper of HDR-NeRF (per sample) and HDR-GS (per Gaussian): 1 -> hidden -> 1, Sigmoid.
    """

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.hidden = PerChannelLinear(1, hidden)
        self.out = PerChannelLinear(hidden, 1)

    def forward(self, log_exposure: Tensor) -> Tensor:
        ldr = torch.sigmoid(self.out(F.relu(self.hidden(channels_first(log_exposure)))))
        return channels_last(ldr.squeeze(-1), log_exposure.shape)
