"""Details of the converters and methods that the training and evaluation tests do not reach:
initialisation, default widths, auxiliary (coarse) renders, the log-radiance cap, schedules."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from mono_hdr_plugin.core.backbone import LdrFeatures, SceneInfo
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.converters import (
    H2LColorConverter,
    L2HColorConverter,
    PerChannelCRF,
    PerChannelLinear,
    PlainH2L,
    PlainL2H,
)
from mono_hdr_plugin.core.losses import LOG_FLOOR, photometric_loss
from mono_hdr_plugin.core.metrics import ssim
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.methods.base import MethodConfig, MethodOutput, Targets, build_method
from mono_hdr_plugin.methods.hdr_nerf import HdrNerfBaseline, HdrNerfOptions
from mono_hdr_plugin.training.pipeline import Pipeline


class TestConverterConstruction:
    def test_per_channel_linear_initialises_as_nn_linear(self):
        """uniform(-1/sqrt(in), 1/sqrt(in)) for weights and biases, one independent layer per channel."""
        torch.manual_seed(0)
        layer = PerChannelLinear(64, 200)
        bound = 1 / math.sqrt(64)
        assert layer.weight.shape == (3, 64, 200) and layer.bias.shape == (3, 1, 200)
        for values in (layer.weight, layer.bias):
            assert values.abs().max() <= bound
            assert values.min() < -0.9 * bound and values.max() > 0.9 * bound
            assert abs(values.mean().item()) < 0.1 * bound
        assert not torch.equal(layer.weight[0], layer.weight[1])

    def test_per_channel_linear_is_three_linear_layers(self):
        layer = PerChannelLinear(2, 5)
        x = torch.rand(3, 7, 2)
        expected = torch.stack([x[c] @ layer.weight[c] + layer.bias[c] for c in range(3)])
        torch.testing.assert_close(layer(x), expected)

    @pytest.mark.parametrize("cls", [L2HColorConverter, H2LColorConverter, PlainL2H, PlainH2L, PerChannelCRF])
    def test_default_width_is_the_papers(self, cls):
        widths = {p.shape[-1] for p in cls().parameters()} | {p.shape[0] for p in cls().parameters() if p.dim() == 2}
        assert 128 in widths

    def test_plain_h2l_is_linear_relu_linear_sigmoid(self):
        converter = PlainH2L(hidden=6)
        first, _, second = converter.net
        x = torch.rand(5, 3) * 2 - 1  # negative inputs too, so the ReLU matters
        expected = torch.sigmoid(second(F.relu(first(x))))
        torch.testing.assert_close(converter(x), expected)


def fake_features(weights: torch.Tensor, raw: torch.Tensor) -> LdrFeatures:
    return LdrFeatures(
        colors=torch.sigmoid(raw),
        raw_colors=raw,
        composite=lambda values: (weights @ values).reshape(4, 4, values.shape[-1]),
    )


class TestAuxiliaryRenders:
    """NeRF's coarse network: rendered like the fine one, supervised with the LDR loss only."""

    @pytest.mark.parametrize("method", ["mono", "hdr-nerf"])
    def test_auxiliary_ldr_and_its_loss(self, method):
        generator = torch.Generator().manual_seed(2)
        weights = torch.rand(16, 5, generator=generator) / 5
        fine = fake_features(weights, torch.randn(5, 3, generator=generator))
        coarse = fake_features(weights.flip(0), torch.randn(5, 3, generator=generator))
        fine.auxiliary = [coarse]
        model = build_method(MethodConfig(method=method), "mse")
        output = model.render(fine, exposure=2.0)
        torch.testing.assert_close(output.auxiliary_ldr[0], model(coarse, 2.0).ldr)
        assert not torch.allclose(output.auxiliary_ldr[0], output.ldr)
        targets = Targets(ldr=torch.rand(4, 4, 3), exposure=2.0, hdr=torch.rand(4, 4, 3) * 5)
        terms = model.losses(output, targets, step=0)
        torch.testing.assert_close(terms["ldr_aux0"], ((output.auxiliary_ldr[0] - targets.ldr) ** 2).mean())
        assert not any(name.startswith(("hdr_aux", "h2l_aux")) for name in terms)


class TestBaselineDetails:
    def test_log_radiance_is_capped_at_30(self):
        """exp(30) ~ 1e13 is the brightest radiance a baseline renders: finite in float32."""
        weights = torch.full((16, 2), 0.5)
        features = fake_features(weights, torch.tensor([[1e4, 40.0, 29.0], [-3.0, 30.5, 0.0]]))
        output = build_method(MethodConfig(method="hdr-gs"), "l1_dssim")(features, 1.0)
        capped = torch.exp(torch.tensor([[30.0, 30.0, 29.0], [-3.0, 30.0, 0.0]]))
        torch.testing.assert_close(output.hdr, (weights @ capped).reshape(4, 4, 3), rtol=1e-6, atol=0)

    @pytest.mark.parametrize("warmup,step,factor", [(0, 0, 1.0), (1, 0, 1.0), (4, 0, 0.25), (4, 2, 0.75), (4, 3, 1.0)])
    def test_crf_warmup(self, warmup, step, factor):
        method = HdrNerfBaseline(
            MethodConfig(method="hdr-nerf", options=HdrNerfOptions(crf_warmup_steps=warmup)), "mse"
        )
        assert method.learning_rate("method", step, 2.0) == pytest.approx(2.0 * factor)


def test_photometric_loss_default_is_the_3dgs_mix():
    pred, target = torch.rand(12, 12, 3), torch.rand(12, 12, 3)
    expected = 0.8 * (pred - target).abs().mean() + 0.2 * (1 - ssim(pred, target))
    torch.testing.assert_close(photometric_loss(pred, target, "l1_dssim"), expected)


class TestRelativeHdrTerm:
    """--hdr-log-weight W adds W x the scale-invariant log error over the pixels the photo exposes well."""

    def terms(self, weight: float, prediction: torch.Tensor, truth: torch.Tensor, photo: torch.Tensor) -> dict:
        method = build_method(MethodConfig(method="mono", hdr_log_weight=weight), "mse")
        return method.losses(MethodOutput(ldr=photo, hdr=prediction), Targets(photo, 1.0, truth), step=0)

    def test_counts_only_well_exposed_pixels(self):
        truth = torch.rand(8, 8, 3) + 0.1
        photo = torch.full((8, 8, 3), 0.5)
        photo[:4] = 1.0  # clipped: the photo holds no colour there
        wrong_where_clipped = truth.clone()
        wrong_where_clipped[:4, :, 0] = 0.0
        assert self.terms(0.5, wrong_where_clipped, truth, photo)["hdr_log"].item() == 0.0
        wrong_where_exposed = truth.clone()
        wrong_where_exposed[4:, :, 0] *= 0.01
        # numpy, from the definition over the exposed half: a third of its entries off by 100x, median 0
        exposed = truth[4:].double().numpy()
        floor = LOG_FLOOR * exposed.mean()
        red = exposed[..., 0]
        expected = 0.5 * np.abs(np.log(0.01 * red + floor) - np.log(red + floor)).sum() / exposed.size
        assert self.terms(0.5, wrong_where_exposed, truth, photo)["hdr_log"].item() == pytest.approx(expected, rel=1e-3)

    def test_off_by_default_and_without_exposed_pixels(self):
        truth = torch.rand(8, 8, 3) + 0.1
        assert "hdr_log" not in self.terms(0.0, truth * 2, truth, torch.full((8, 8, 3), 0.5))
        assert "hdr_log" not in self.terms(0.5, truth * 2, truth, torch.ones(8, 8, 3))

    @pytest.mark.parametrize(
        ("backbone", "unbounded", "expected"),
        [("nerf", True, 0.01), ("nerf", False, 0.0), ("gs", True, 0.01), ("gs", False, 0.0)],
    )
    def test_default_weight_is_on_under_an_open_sky_only(self, backbone, unbounded, expected):
        """The documented defaults (docs/outdoor.md): 0.01 on an unbounded scene, off on interiors;
        a weight given on the command line is kept."""
        cameras = [
            Camera(look_at(torch.tensor([x, -4.0, 0.5]), torch.zeros(3)), 20.0, 20.0, 8.0, 8.0, 16, 16)
            for x in (-1.0, 0.0, 1.0)
        ]
        scene = SceneInfo(
            bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=cameras, unbounded=unbounded
        )
        config = get_backbone(backbone).config_class()
        chosen = Pipeline.create(backbone, config, MethodConfig(method="mono"), scene).method.config.hdr_log_weight
        assert chosen == expected
        given = Pipeline.create(backbone, config, MethodConfig(method="mono", hdr_log_weight=0.2), scene)
        assert given.method.config.hdr_log_weight == 0.2
