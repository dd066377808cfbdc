"""Colour converters of Mono-HDR-3D (docs/method.md) and their ablation twins.

L2H-CC mirrors the inverted imaging equation I_h = X * S(I_l) + Y, one small network per
colour channel; H2L-CC mirrors I_l = D(I_h) + B(I_h) and closes the loop. The plain MLPs
have the same width and input/output ranges but none of that structure (paper, Table 4).

The per-channel networks (L2H-CC, its plain twin, the baselines' CRF) run once per primitive,
so they dominate a step when evaluated as matrix products. Each maps one number to a few
through Linear -> ReLU -> Linear, which is a piecewise-linear function with one kink per
hidden unit: `per_channel_relu_mlp` evaluates it exactly that way (a table of slopes and
intercepts between the sorted kinks, one lookup per input), with gradients for every weight.
"""

import math
from pathlib import Path

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


def per_channel_relu_mlp(x: Tensor, first: PerChannelLinear, second: PerChannelLinear) -> Tensor:
    """second(relu(first(x))) for one scalar per channel: x [C, N] -> [C, N, K]."""
    return relu_mlp_by_intervals(x, first.weight, first.bias, second.weight, second.bias)


def relu_mlp_by_intervals(x: Tensor, weight1: Tensor, bias1: Tensor, weight2: Tensor, bias2: Tensor) -> Tensor:
    """relu(x w1 + b1) w2 + b2 per channel, x [C, N] -> [C, N, K], from PerChannelLinear-shaped weights
    (w1, b1 [C, 1, H]; w2 [C, H, K]; b2 [C, 1, K]).

    Between consecutive kinks t_j = -b_j / w_j of the hidden units the active set is fixed, so
    the output is slope * x + intercept there. Positive-slope units are active above their kink,
    negative ones below it; prefix sums over the sorted kinks give every interval's slope and
    intercept (computed in float64), and each input looks its interval up. Equal to the matrix
    form up to rounding, at O(N + hidden) cost instead of O(N * hidden).
    """
    w1, b1 = weight1[:, 0, :].double(), bias1[:, 0, :].double()  # [C, H]
    w2, b2 = weight2.double(), bias2.double()  # [C, H, K], [C, 1, K]
    moving = w1 != 0
    # a unit with w = 0 never switches: "rising" from -inf when on (b > 0), from +inf when off
    kinks = torch.where(moving, -b1 / torch.where(moving, w1, 1.0), torch.where(b1 > 0, -torch.inf, torch.inf))
    order = torch.argsort(kinks, dim=1)
    sorted_kinks = kinks.gather(1, order)

    def by_kink(values: Tensor) -> Tensor:  # [C, H] -> [C, H] in kink order
        return values.gather(1, order)

    rising, falling = by_kink((w1 >= 0).double())[..., None], by_kink((w1 < 0).double())[..., None]
    slopes = by_kink(w1)[..., None] * w2.gather(1, order[..., None].expand_as(w2))  # [C, H, K]
    offsets = by_kink(b1)[..., None] * w2.gather(1, order[..., None].expand_as(w2))
    zero = slopes.new_zeros(slopes.shape[0], 1, slopes.shape[2])

    def table(contribution: Tensor) -> Tensor:
        """Interval k (k kinks below x): rising units before k plus falling units from k on."""
        below = torch.cat([zero, torch.cumsum(rising * contribution, 1)], 1)
        above_total = (falling * contribution).sum(1, keepdim=True)
        falling_below = torch.cat([zero, torch.cumsum(falling * contribution, 1)], 1)
        return below + above_total - falling_below  # [C, H + 1, K]

    slope_table = table(slopes).to(x.dtype)
    intercept_table = (table(offsets) + b2).to(x.dtype)
    interval = torch.searchsorted(sorted_kinks.to(x.dtype).contiguous(), x.detach().contiguous())
    index = interval[..., None].expand(-1, -1, slope_table.shape[2])
    return slope_table.gather(1, index) * x[..., None] + intercept_table.gather(1, index)


def channels_first(colors: Tensor) -> Tensor:
    """[..., 3] -> [3, N, 1], the layout PerChannelLinear works in."""
    return colors.reshape(-1, colors.shape[-1]).T.unsqueeze(-1)


def channels_last(values: Tensor, shape: torch.Size) -> Tensor:
    """[3, N] -> [..., 3] with the leading shape of the original colours."""
    return values.T.reshape(shape)


class L2HColorConverter(nn.Module):
    """L2H-CC: LDR colour [..., 3] in [0, 1] -> HDR colour [..., 3] >= 0, per channel, non-decreasing.

    It also takes a monotone coordinate of the LDR colour in place of it, as the NeRF grid field's
    logits (LdrFeatures.l2h_inputs): the same information, better conditioned near 1.

    latent = ReLU(W x); X = ReLU(.), S = ReLU(.), Y = linear; out = Softplus(x + X * S + Y).
    The three heads share one [hidden -> 3] product (columns X, S, Y), the same maths as
    three Linear(hidden -> 1) layers at a third of the memory traffic.

    L2H-CC stands in for the inverse of a camera response, which rises; the paper's network can
    fall, and then a brighter photo maps to a darker radiance (docs/method.md, "A monotone L2H-CC").
    So each hidden unit has a fixed direction: the first half rise with the input (latent weight
    |w|), the second half fall (-|w|), and the unit's three head weights carry its direction's sign
    (+|a| or -|a|). Every unit then adds a non-decreasing function to X, S and Y; ReLU(X) * ReLU(S)
    is a product of non-negative non-decreasing functions, and x, the sum and Softplus rise: the
    output never falls as the input rises, whatever the weights, while rising and falling units
    together still draw any non-decreasing piecewise-linear X, S and Y.
    """

    direction: Tensor

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.latent = PerChannelLinear(1, hidden)
        self.heads = PerChannelLinear(hidden, 3)
        direction = torch.where(torch.arange(hidden) < (hidden + 1) // 2, 1.0, -1.0)
        self.register_buffer("direction", direction, persistent=False)  # a function of `hidden` alone

    def monotone_weights(self) -> tuple[Tensor, Tensor]:
        """The latent [C, 1, H] and head [C, H, 3] weights the converter applies (signed by unit direction)."""
        return self.direction * self.latent.weight.abs(), self.direction[:, None] * self.heads.weight.abs()

    def forward(self, ldr: Tensor) -> Tensor:
        x = channels_first(ldr).squeeze(-1)
        latent_weight, head_weight = self.monotone_weights()
        heads = relu_mlp_by_intervals(x, latent_weight, self.latent.bias, head_weight, self.heads.bias)
        gain, saturation, noise = heads.unbind(-1)
        hdr = F.softplus(x + F.relu(gain) * F.relu(saturation) + noise)
        return channels_last(hdr, ldr.shape)


class H2LColorConverter(nn.Module):
    """H2L-CC: normalised HDR pixel [..., 3] -> LDR pixel [..., 3] in (0, 1).

    latent = ReLU(W x); D = ReLU(.), B = Tanh(.); out = Sigmoid(D + B). On the CPU it runs the fused
    C++ kernel (`h2l_cc`); elsewhere, and as the kernel's test twin, `h2l_cc_reference`.
    """

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.latent = nn.Linear(3, hidden)
        self.response = nn.Linear(hidden, 3)
        self.bias = nn.Linear(hidden, 3)

    def forward(self, hdr: Tensor) -> Tensor:
        # both heads in one [6, hidden] matrix: R (the response D) then B
        head_weight = torch.cat([self.response.weight, self.bias.weight])
        head_bias = torch.cat([self.response.bias, self.bias.bias])
        convert = h2l_cc if hdr.device.type == "cpu" else h2l_cc_reference
        return convert(hdr, self.latent.weight, self.latent.bias, head_weight, head_bias)


def h2l_cc_reference(hdr: Tensor, latent_weight: Tensor, latent_bias: Tensor, head_weight: Tensor, head_bias: Tensor):
    """H2L-CC in torch layers: Sigmoid(ReLU(R) + Tanh(B)), [R, B] = head_weight ReLU(latent_weight x + b) + b'."""
    heads = F.linear(F.relu(F.linear(hdr, latent_weight, latent_bias)), head_weight, head_bias)
    response, bias = heads.split(3, dim=-1)
    return torch.sigmoid(F.relu(response) + torch.tanh(bias))


def h2l_cc(hdr: Tensor, latent_weight: Tensor, latent_bias: Tensor, head_weight: Tensor, head_bias: Tensor):
    """`h2l_cc_reference` by the fused C++ kernel (CPU): no [pixels, hidden] latent is kept, the backward
    pass recomputes it per pixel (3.4-3.9x faster than autograd through the layers at 512-1024 px:
    benchmarks/results/loss_kernels)."""
    inputs = (hdr.reshape(-1, 3), latent_weight, latent_bias, head_weight, head_bias)
    return _FusedH2L.apply(*(tensor.contiguous() for tensor in inputs)).view(hdr.shape)


class _FusedH2L(torch.autograd.Function):
    @staticmethod
    def forward(ctx, hdr, latent_weight, latent_bias, head_weight, head_bias):
        ctx.save_for_backward(hdr, latent_weight, latent_bias, head_weight, head_bias)
        return _h2l_extension().h2l_forward(hdr, latent_weight, latent_bias, head_weight, head_bias)

    @staticmethod
    def backward(ctx, grad_out):
        return tuple(_h2l_extension().h2l_backward(grad_out.contiguous(), *ctx.saved_tensors))


def _h2l_extension():
    from mono_hdr_plugin.core.cpp_extensions import load_cpp_extension

    return load_cpp_extension("h2l_cc", Path(__file__).parent / "csrc" / "h2l_cc.cpp")


class PlainL2H(nn.Module):
    """Ablation: a plain per-channel MLP (1 -> hidden -> 1, Softplus out), no imaging structure and,
    as in the paper, no monotonicity: it may map a brighter colour to a darker radiance."""

    def __init__(self, hidden: int = 128):
        super().__init__()
        self.hidden = PerChannelLinear(1, hidden)
        self.out = PerChannelLinear(hidden, 1)

    def forward(self, ldr: Tensor) -> Tensor:
        hdr = F.softplus(per_channel_relu_mlp(channels_first(ldr).squeeze(-1), self.hidden, self.out))
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
        ldr = torch.sigmoid(per_channel_relu_mlp(channels_first(log_exposure).squeeze(-1), self.hidden, self.out))
        return channels_last(ldr.squeeze(-1), log_exposure.shape)
