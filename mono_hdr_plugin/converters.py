"""Colour converters of Mono-HDR-3D (REFERENCE.md section 1) and their ablation twins.

L2H-CC mirrors the inverted imaging equation I_h = X * S(I_l) + Y, one small network per
colour channel; H2L-CC mirrors I_l = D(I_h) + B(I_h) and closes the loop. The plain MLPs
have the same width and input/output ranges but none of that structure (paper, Table 4).
"""

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class PerChannelLinear(nn.Module):
    """Three independent Linear(in_features -> out_features) layers, one per colour channel.

    Input [..., 3, in_features] -> output [..., 3, out_features]. Batched with einsum so the
    three "1 -> 128 -> 1" networks of the official code cost one matrix product.
    """

    def __init__(self, in_features: int, out_features: int, channels: int = 3):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)  # nn.Linear's default initialisation
        self.weight = nn.Parameter(torch.empty(channels, in_features, out_features).uniform_(-bound, bound))
        self.bias = nn.Parameter(torch.empty(channels, out_features).uniform_(-bound, bound))

    def forward(self, x: Tensor) -> Tensor:
        return torch.einsum("...ci,cio->...co", x, self.weight) + self.bias


class L2HColorConverter(nn.Module):
    """L2H-CC: LDR colour [..., 3] in [0, 1] -> HDR colour [..., 3] >= 0, per channel.

    latent = ReLU(W x); X = ReLU(.), S = ReLU(.), Y = linear; out = Softplus(x + X * S + Y).
    """

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.latent = PerChannelLinear(1, hidden)
        self.gain = PerChannelLinear(hidden, 1)
        self.saturation = PerChannelLinear(hidden, 1)
        self.noise = PerChannelLinear(hidden, 1)

    def forward(self, ldr: Tensor) -> Tensor:
        x = ldr.unsqueeze(-1)
        latent = F.relu(self.latent(x))
        gain, saturation = F.relu(self.gain(latent)), F.relu(self.saturation(latent))
        return F.softplus(x + gain * saturation + self.noise(latent)).squeeze(-1)


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
        return F.softplus(self.out(F.relu(self.hidden(ldr.unsqueeze(-1))))).squeeze(-1)


class PlainH2L(nn.Module):
    """Ablation: a plain MLP (3 -> hidden -> 3, Sigmoid out) in place of H2L-CC."""

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(3, hidden), nn.ReLU(), nn.Linear(hidden, 3))

    def forward(self, hdr: Tensor) -> Tensor:
        return torch.sigmoid(self.net(hdr))


class PerChannelCRF(nn.Module):
    """Learned camera response per channel: log exposure [..., 3] -> LDR [..., 3] in (0, 1).

    The tone mapper of HDR-NeRF (per sample) and HDR-GS (per pixel): 1 -> hidden -> 1, Sigmoid.
    """

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.hidden = PerChannelLinear(1, hidden)
        self.out = PerChannelLinear(hidden, 1)

    def forward(self, log_exposure: Tensor) -> Tensor:
        return torch.sigmoid(self.out(F.relu(self.hidden(log_exposure.unsqueeze(-1))))).squeeze(-1)
