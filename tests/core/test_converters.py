import copy
import math

import pytest
import torch
import torch.nn.functional as F

from mono_hdr_plugin.core.converters import (
    H2LColorConverter,
    L2HColorConverter,
    PerChannelCRF,
    PerChannelLinear,
    PlainH2L,
    PlainL2H,
    h2l_cc,
    h2l_cc_reference,
    per_channel_relu_mlp,
)


def reference_l2h(converter: L2HColorConverter, ldr: torch.Tensor) -> torch.Tensor:
    """The official per-channel loop (three separate 1 -> hidden -> (X, S, Y) networks) on the weights
    the recipe in MonoHDR.hdr_recipe describes: unit j rises (+|w|, +|a|) for j < ceil(hidden / 2),
    else falls (-|w|, -|a|)."""
    hidden = converter.latent.weight.shape[-1]
    sign = torch.tensor([1.0 if j < math.ceil(hidden / 2) else -1.0 for j in range(hidden)], dtype=ldr.dtype)
    outputs = []
    for c in range(3):
        x = ldr[..., c : c + 1]
        latent = F.relu(x @ (sign * converter.latent.weight[c].abs()) + converter.latent.bias[c])
        heads = latent @ (sign[:, None] * converter.heads.weight[c].abs()) + converter.heads.bias[c]
        gain, saturation, noise = F.relu(heads[..., 0:1]), F.relu(heads[..., 1:2]), heads[..., 2:3]
        outputs.append(F.softplus(x + gain * saturation + noise))
    return torch.cat(outputs, -1)


def matrix_form(x: torch.Tensor, first: PerChannelLinear, second: PerChannelLinear) -> torch.Tensor:
    """second(relu(first(x))) as two batched matrix products: x [C, N] -> [C, N, K]."""
    return second(F.relu(first(x[..., None])))


class TestPerChannelReluMlp:
    @pytest.mark.parametrize("heads", [1, 3])
    def test_values_and_gradients_match_the_matrix_form(self, heads):
        torch.manual_seed(3)
        first, second = PerChannelLinear(1, 64), PerChannelLinear(64, heads)
        with torch.no_grad():
            first.weight[1, 0, :5] = 0.0  # units that never switch: constant on or off
            first.bias[1, 0, :3] = 0.4
            first.bias[1, 0, 3:5] = -0.4
        x = torch.cat([torch.rand(3, 200) * 6 - 3, torch.tensor([[0.0], [10.0], [-10.0]])], 1)
        weights = torch.rand(3, 201, heads)
        outputs, grads = [], []
        for evaluate in (per_channel_relu_mlp, matrix_form):
            leaf = x.clone().requires_grad_()
            for module in (first, second):
                module.zero_grad()
            out = evaluate(leaf, first, second)
            (out * weights).sum().backward()
            outputs.append(out)
            grads.append([leaf.grad] + [p.grad.clone() for p in (*first.parameters(), *second.parameters())])
        assert outputs[0].shape == (3, 201, heads)
        torch.testing.assert_close(outputs[0], outputs[1], rtol=1e-5, atol=1e-5)
        for got, want in zip(*grads):
            torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-4)

    def test_float64_inputs_keep_float64_accuracy(self):
        # The interval tables are prefix sums over 128 units: in float32 they would be off by ~1e-7.
        torch.manual_seed(4)
        first, second = PerChannelLinear(1, 128), PerChannelLinear(128, 3)
        with torch.no_grad():
            first.weight[0, 0, 0] = 1.0  # a unit of slope exactly 1 still switches at its kink
            first.bias[0, 0, 0] = -0.25
        x = torch.cat(
            [
                torch.rand(3, 500, dtype=torch.float64) * 4 - 2,
                torch.full((3, 2), 0.25, dtype=torch.float64) + torch.tensor([-1e-3, 1e-3]),
            ],
            1,
        )
        exact = matrix_form(x, copy.deepcopy(first).double(), copy.deepcopy(second).double())
        torch.testing.assert_close(per_channel_relu_mlp(x, first, second), exact, rtol=1e-12, atol=1e-12)

    def test_inputs_on_a_kink_are_continuous(self):
        first, second = PerChannelLinear(1, 8), PerChannelLinear(8, 2)
        kinks = -first.bias[:, 0, :] / first.weight[:, 0, :]
        x = kinks.detach()
        torch.testing.assert_close(
            per_channel_relu_mlp(x, first, second), matrix_form(x, first, second), rtol=1e-5, atol=1e-5
        )

    def test_gradcheck(self):
        first, second = PerChannelLinear(1, 6).double(), PerChannelLinear(6, 3).double()
        x = torch.rand(3, 5, dtype=torch.float64, requires_grad=True)
        params = (first.weight, first.bias, second.weight, second.bias)
        assert torch.autograd.gradcheck(lambda x: per_channel_relu_mlp(x, first, second), (x,))
        assert torch.autograd.gradcheck(
            lambda w1, b1, w2, b2: _functional(x.detach(), w1, b1, w2, b2),
            tuple(p.detach().clone().requires_grad_() for p in params),
        )


def _functional(x, w1, b1, w2, b2):
    """per_channel_relu_mlp as a function of the weights, for gradcheck."""
    first, second = PerChannelLinear(1, w1.shape[2]).double(), PerChannelLinear(w1.shape[2], w2.shape[2]).double()
    del first.weight, first.bias, second.weight, second.bias
    first.weight, first.bias, second.weight, second.bias = w1, b1, w2, b2
    return per_channel_relu_mlp(x, first, second)


class TestL2HColorConverter:
    def test_shapes_any_leading_dims(self):
        converter = L2HColorConverter(hidden=16)
        for shape in [(5, 3), (2, 7, 3), (3,)]:
            assert converter(torch.rand(shape)).shape == shape

    def test_matches_per_channel_loop(self):
        torch.manual_seed(0)
        converter = L2HColorConverter(hidden=32)
        ldr = torch.rand(4, 9, 3)
        torch.testing.assert_close(converter(ldr), reference_l2h(converter, ldr))

    def test_channels_are_independent(self):
        converter = L2HColorConverter(hidden=8)
        ldr = torch.rand(10, 3)
        changed = ldr.clone()
        changed[:, 1] = torch.rand(10)
        out_a, out_b = converter(ldr), converter(changed)
        torch.testing.assert_close(out_a[:, [0, 2]], out_b[:, [0, 2]])
        assert not torch.allclose(out_a[:, 1], out_b[:, 1])

    def test_output_non_negative_on_extremes(self):
        converter = L2HColorConverter(hidden=8)
        with torch.no_grad():
            converter.heads.bias.fill_(-50.0)
        out = converter(torch.tensor([[0.0, 0.5, 1.0]]))
        assert (out >= 0).all() and torch.isfinite(out).all()

    def test_gradcheck(self):
        converter = L2HColorConverter(hidden=6).double()
        ldr = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(converter, (ldr,))

    def test_weights_get_gradients(self):
        converter = L2HColorConverter(hidden=8)
        converter(torch.rand(20, 3)).sum().backward()
        for parameter in converter.parameters():
            assert parameter.grad is not None and parameter.grad.abs().sum() > 0


def largest_fall(converter, inputs: torch.Tensor) -> float:
    """The largest drop of the converter's output between consecutive sorted inputs [N] (all channels)."""
    with torch.no_grad():
        out = converter(inputs[:, None].expand(-1, 3).contiguous())
    return float((out[:-1] - out[1:]).clamp_min(0).max())


class TestL2HMonotone:
    """L2H-CC stands in for an inverse camera response: never a darker HDR for a brighter colour."""

    INPUTS = torch.linspace(0.0, 1.0, 2001)
    LOGITS = torch.linspace(-12.0, 12.0, 2001)  # the NeRF grid field's monotone coordinate

    @pytest.mark.parametrize("seed", range(6))
    def test_non_decreasing_for_any_weights(self, seed):
        torch.manual_seed(seed)
        converter = L2HColorConverter(hidden=32)
        with torch.no_grad():  # weights far from their initialisation, of both signs, as training leaves them
            for parameter in converter.parameters():
                parameter.copy_(torch.randn_like(parameter) * 3.0)
        assert largest_fall(converter, self.INPUTS) == 0.0
        assert largest_fall(converter, self.LOGITS) == 0.0

    def test_the_plain_ablation_is_not(self):
        # the same check finds falls in the paper's plain MLP: it is the check, not luck, that passes above
        falls = []
        for seed in range(6):
            torch.manual_seed(seed)
            plain = PlainL2H(hidden=32)
            with torch.no_grad():
                for parameter in plain.parameters():
                    parameter.copy_(torch.randn_like(parameter) * 3.0)
            falls.append(largest_fall(plain, self.INPUTS))
        assert max(falls) > 1e-3

    def test_can_fit_a_concave_rise(self):
        # rising and falling units together draw a concave curve (sqrt), which rising units alone cannot
        torch.manual_seed(0)
        converter = L2HColorConverter(hidden=16)
        x = torch.linspace(0.0, 1.0, 64)[:, None].expand(-1, 3).contiguous()
        target = 3.0 * x.sqrt() + 0.05
        optimiser = torch.optim.Adam(converter.parameters(), lr=0.02)
        for _ in range(600):
            optimiser.zero_grad()
            loss = ((converter(x) - target) ** 2).mean()
            loss.backward()
            optimiser.step()
        # a convex (rising units only) fit is at best affine here: mean squared error about 0.02
        assert loss.item() < 5e-3


class TestH2LColorConverter:
    def test_range_and_shape(self):
        converter = H2LColorConverter(hidden=16)
        out = converter(torch.rand(6, 5, 3))  # normalised HDR input lies in [0, 1]
        assert out.shape == (6, 5, 3) and (out > 0).all() and (out < 1).all()

    def test_structure_sigmoid_of_relu_plus_tanh(self):
        converter = H2LColorConverter(hidden=8)
        x = torch.rand(4, 3)
        latent = F.relu(converter.latent(x))
        expected = torch.sigmoid(F.relu(converter.response(latent)) + torch.tanh(converter.bias(latent)))
        torch.testing.assert_close(converter(x), expected)
        # D >= 0 and |B| < 1 bound the output from below by sigmoid(-1)
        assert (converter(torch.rand(100, 3)) > torch.sigmoid(torch.tensor(-1.0))).all()

    def test_gradcheck(self):
        converter = H2LColorConverter(hidden=6).double()
        x = torch.rand(3, 3, dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(converter, (x,))


def layered_h2l(converter: H2LColorConverter, x: torch.Tensor) -> torch.Tensor:
    """H2L-CC through the converter's own nn.Linear layers, as the official code runs it."""
    latent = F.relu(converter.latent(x))
    return torch.sigmoid(F.relu(converter.response(latent)) + torch.tanh(converter.bias(latent)))


class TestH2LKernel:
    """The fused C++ H2L-CC (`h2l_cc`) against the layers it fuses: values and every gradient."""

    @pytest.mark.parametrize("hidden", [128, 7])  # 7: the vector loops' remainder
    def test_values_and_gradients_match_the_layers(self, hidden):
        torch.manual_seed(hidden)
        converter = H2LColorConverter(hidden)
        x = torch.rand(40, 30, 3, requires_grad=True)
        upstream = torch.randn(40, 30, 3)
        parameters = [x, *converter.parameters()]
        fused = converter(x)
        layered = layered_h2l(converter, x)
        torch.testing.assert_close(fused, layered, rtol=1e-6, atol=1e-6)
        fused_grads = torch.autograd.grad(fused, parameters, upstream)
        layered_grads = torch.autograd.grad(layered, parameters, upstream)
        for got, expected in zip(fused_grads, layered_grads, strict=True):
            torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5 * expected.abs().max().item())

    def test_gradcheck_of_every_input_in_double(self):
        torch.manual_seed(1)
        inputs = [
            torch.rand(5, 3, dtype=torch.float64),
            torch.randn(6, 3, dtype=torch.float64),
            torch.randn(6, dtype=torch.float64),
            torch.randn(6, 6, dtype=torch.float64),
            torch.randn(6, dtype=torch.float64),
        ]
        inputs = [t.requires_grad_() for t in inputs]
        assert torch.autograd.gradcheck(h2l_cc, inputs)

    def test_the_same_on_one_thread_and_two(self):
        converter = H2LColorConverter(32)
        x = torch.rand(1000, 3, requires_grad=True)
        results = []
        for threads in (1, 2):
            previous = torch.get_num_threads()
            torch.set_num_threads(threads)
            try:
                out = converter(x)
                results.append([out, *torch.autograd.grad(out.square().sum(), [x, converter.latent.weight])])
            finally:
                torch.set_num_threads(previous)
        for one, two in zip(*results, strict=True):
            torch.testing.assert_close(one, two, rtol=1e-5, atol=1e-6)

    def test_reference_twin_is_the_layers(self):
        converter = H2LColorConverter(16)
        x = torch.rand(8, 3)
        weights = torch.cat([converter.response.weight, converter.bias.weight])
        biases = torch.cat([converter.response.bias, converter.bias.bias])
        reference = h2l_cc_reference(x, converter.latent.weight, converter.latent.bias, weights, biases)
        torch.testing.assert_close(reference, layered_h2l(converter, x))

    def test_an_empty_batch(self):
        converter = H2LColorConverter(8)
        x = torch.rand(0, 3, requires_grad=True)
        out = converter(x)
        out.sum().backward()
        assert out.shape == (0, 3) and converter.latent.weight.grad.abs().sum() == 0


class TestAblationConverters:
    @pytest.mark.parametrize("cls", [PlainL2H, PlainH2L, PerChannelCRF])
    def test_shapes_and_gradcheck(self, cls):
        module = cls(hidden=5).double()
        x = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
        assert module(x).shape == (4, 3)
        assert torch.autograd.gradcheck(module, (x,))

    @pytest.mark.parametrize(("cls", "activation"), [(PlainL2H, F.softplus), (PerChannelCRF, torch.sigmoid)])
    def test_per_channel_linear_relu_linear_then_activation(self, cls, activation):
        converter = cls(hidden=6)
        assert converter.hidden.weight.shape == (3, 1, 6) and converter.out.weight.shape == (3, 6, 1)
        x = torch.rand(5, 3, dtype=torch.float64) * 4 - 2
        hidden, out = converter.hidden, converter.out
        expected = torch.stack(
            [
                activation(
                    F.relu(x[:, c : c + 1] @ hidden.weight[c].double() + hidden.bias[c].double())
                    @ out.weight[c].double()
                    + out.bias[c].double()
                )[:, 0]
                for c in range(3)
            ],
            -1,
        )
        torch.testing.assert_close(converter(x), expected)

    def test_plain_l2h_has_no_residual_structure(self):
        names = {name for name, _ in PlainL2H(4).named_parameters()}
        assert not any("heads" in name for name in names)

    def test_crf_output_in_unit_interval(self):
        out = PerChannelCRF(8)(torch.linspace(-20, 20, 30).reshape(10, 3))
        assert (out >= 0).all() and (out <= 1).all()
