import pytest
import torch
import torch.nn.functional as F

from mono_hdr_plugin.converters import (H2LColorConverter, L2HColorConverter, PerChannelCRF, PlainH2L, PlainL2H)


def reference_l2h(converter: L2HColorConverter, ldr: torch.Tensor) -> torch.Tensor:
    """The official per-channel loop: three separate 1 -> hidden -> (X, S, Y) networks."""
    outputs = []
    for c in range(3):
        x = ldr[..., c:c + 1]
        latent = F.relu(x @ converter.latent.weight[c] + converter.latent.bias[c])
        heads = latent @ converter.heads.weight[c] + converter.heads.bias[c]
        gain, saturation, noise = F.relu(heads[..., 0:1]), F.relu(heads[..., 1:2]), heads[..., 2:3]
        outputs.append(F.softplus(x + gain * saturation + noise))
    return torch.cat(outputs, -1)


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


class TestAblationConverters:
    @pytest.mark.parametrize("cls", [PlainL2H, PlainH2L, PerChannelCRF])
    def test_shapes_and_gradcheck(self, cls):
        module = cls(hidden=5).double()
        x = torch.rand(4, 3, dtype=torch.float64, requires_grad=True)
        assert module(x).shape == (4, 3)
        assert torch.autograd.gradcheck(module, (x,))

    def test_plain_l2h_has_no_residual_structure(self):
        names = {name for name, _ in PlainL2H(4).named_parameters()}
        assert not any("heads" in name for name in names)

    def test_crf_output_in_unit_interval(self):
        out = PerChannelCRF(8)(torch.linspace(-20, 20, 30).reshape(10, 3))
        assert (out >= 0).all() and (out <= 1).all()
