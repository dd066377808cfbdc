"""The meta-algorithm wrapper and the baselines, on a fake backbone whose compositing we know."""

import math

import pytest
import torch

from mono_hdr_plugin.core.backbone import LdrFeatures
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.core.registry import RegistryError
from mono_hdr_plugin.core.validation import FlagError, check_flags
from mono_hdr_plugin.methods.base import MethodConfig, MethodOutput, Targets, build_method, method_names
from mono_hdr_plugin.methods.hdr_gs import HdrGsBaseline
from mono_hdr_plugin.methods.hdr_nerf import HdrNerfBaseline, HdrNerfOptions
from mono_hdr_plugin.methods.mono import MonoHDR


def fake_features(pixels: int = 12, primitives: int = 5, seed: int = 0):
    """Per-pixel weights [pixels, P] over P primitives; composite = weights @ values; counts calls."""
    generator = torch.Generator().manual_seed(seed)
    weights = torch.rand(pixels * pixels, primitives, generator=generator)
    weights = weights / weights.sum(-1, keepdim=True) * 0.9
    raw = torch.randn(primitives, 3, generator=generator, requires_grad=True)
    calls = []

    def composite(values):
        calls.append(values.shape[-1])
        return (weights @ values).reshape(pixels, pixels, values.shape[-1])

    return LdrFeatures(colors=torch.sigmoid(raw), raw_colors=raw, composite=composite), calls, weights


class TestMonoHDR:
    def test_single_compositing_pass_with_six_channels(self):
        features, calls, _ = fake_features()
        MonoHDR(MethodConfig(), "l1_dssim")(features, exposure=1.0)
        assert calls == [6]

    def test_composite_once_equals_composite_twice(self):
        features, _, _ = fake_features()
        method = MonoHDR(MethodConfig(), "l1_dssim")
        once = method(features, exposure=1.0)
        ldr_twice = features.composite(features.colors)
        hdr_twice = features.composite(method.l2h(features.colors))
        torch.testing.assert_close(once.ldr, ldr_twice)
        torch.testing.assert_close(once.hdr, hdr_twice)

    def test_l2h_reads_the_backbones_l2h_inputs_when_given(self):
        features, calls, weights = fake_features()
        features.l2h_inputs = features.raw_colors
        method = MonoHDR(MethodConfig(), "mse")
        out = method(features, exposure=1.0)
        assert calls == [6]
        torch.testing.assert_close(out.hdr, (weights @ method.l2h(features.raw_colors)).reshape(out.hdr.shape))
        torch.testing.assert_close(out.ldr, (weights @ features.colors).reshape(out.ldr.shape))
        assert not torch.allclose(out.hdr, (weights @ method.l2h(features.colors)).reshape(out.hdr.shape))

    def test_logit_input_keeps_the_hdr_gradient_of_saturated_colours(self):
        """A sample at logit 8 has an LDR colour of 0.9997: through the sigmoid the HDR loss can
        hardly move it (sigmoid' = 3e-4), through the logit it can."""
        raw = torch.full((1, 3), 8.0, requires_grad=True)
        method = MonoHDR(MethodConfig(), "mse")
        gradients = {}
        for name, l2h_inputs in (("colors", None), ("logits", raw)):
            features = LdrFeatures(
                colors=torch.sigmoid(raw), raw_colors=raw, composite=lambda values: values, l2h_inputs=l2h_inputs
            )
            raw.grad = None
            method(features, 1.0).hdr.sum().backward()
            gradients[name] = raw.grad.abs().sum().item()
        assert gradients["logits"] > 100 * gradients["colors"]

    def test_h2l_applied_to_normalised_hdr(self):
        features, _, _ = fake_features()
        method = MonoHDR(MethodConfig(), "l1_dssim")
        out = method(features, exposure=1.0)
        torch.testing.assert_close(out.ldr_from_hdr, method.h2l(normalise_hdr(out.hdr)))

    def test_ldr_output_ignores_exposure(self):
        features, _, _ = fake_features()
        method = MonoHDR(MethodConfig(), "mse")
        torch.testing.assert_close(method(features, 0.125).ldr, method(features, 32.0).ldr)

    @pytest.mark.parametrize("name,has_h2l", [("mono", True), ("mlp-l2h", True), ("mlp-h2l", True), ("no-h2l", False)])
    def test_ablation_variants(self, name, has_h2l):
        method = build_method(MethodConfig(method=name), "l1_dssim")
        assert (method.h2l is not None) == has_h2l
        assert type(method.l2h).__name__ == ("PlainL2H" if name == "mlp-l2h" else "L2HColorConverter")
        if name == "mlp-h2l":
            assert type(method.h2l).__name__ == "PlainH2L"


class TestLossTerms:
    def _terms(self, config: MethodConfig, with_hdr: bool = True, kind: str = "l1_dssim"):
        features, _, _ = fake_features()
        method = build_method(config, kind)
        output = method.render(features, exposure=0.5)
        targets = Targets(ldr=torch.rand(12, 12, 3), exposure=0.5, hdr=torch.rand(12, 12, 3) * 10 if with_hdr else None)
        return method.losses(output, targets, step=0), method, output, targets

    def test_all_three_terms_with_paper_weights(self):
        terms, method, output, targets = self._terms(MethodConfig())
        assert set(terms) == {"ldr", "hdr", "h2l"}
        assert method.beta == 0.05
        expected_hdr = 0.6 * method._loss(normalise_hdr(output.hdr), normalise_hdr(targets.hdr))
        torch.testing.assert_close(terms["hdr"], expected_hdr)

    def test_nerf_default_beta(self):
        _, method, _, _ = self._terms(MethodConfig(), kind="mse")
        assert method.beta == 0.01 and method.loss_kind == "mse"

    @pytest.mark.parametrize("ldr,hdr,h2l", [(a, b, c) for a in (0, 1) for b in (0, 1) for c in (0, 1) if a + b + c])
    def test_each_switch_controls_its_term(self, ldr, hdr, h2l):
        config = MethodConfig(use_ldr_loss=bool(ldr), use_hdr_loss=bool(hdr), use_h2l_loss=bool(h2l))
        terms, *_ = self._terms(config)
        assert set(terms) == {name for name, on in (("ldr", ldr), ("hdr", hdr), ("h2l", h2l)) if on}

    def test_no_hdr_term_without_ground_truth(self):
        terms, *_ = self._terms(MethodConfig(), with_hdr=False)
        assert "hdr" not in terms and "h2l" in terms

    def test_h2l_loss_trains_l2h_without_hdr_data(self):
        terms, method, _, _ = self._terms(MethodConfig(use_ldr_loss=False), with_hdr=False)
        terms["h2l"].backward()
        assert method.l2h.latent.weight.grad.abs().sum() > 0


class TestBaselines:
    def test_hdr_nerf_applies_crf_per_primitive(self):
        features, calls, weights = fake_features()
        method = HdrNerfBaseline(MethodConfig(method="hdr-nerf"), "mse")
        out = method(features, exposure=2.0)
        assert calls == [6]
        expected_ldr = (weights @ method.crf(features.raw_colors + math.log(2.0))).reshape(12, 12, 3)
        torch.testing.assert_close(out.ldr, expected_ldr)
        torch.testing.assert_close(out.hdr, (weights @ torch.exp(features.raw_colors)).reshape(12, 12, 3))

    def test_hdr_gs_tone_maps_gaussians_and_composites_linear_radiance(self):
        """As the official HDR-GS renderer: tone mapper per Gaussian, HDR rasterises exp(ln E)."""
        features, calls, weights = fake_features()
        method = HdrGsBaseline(MethodConfig(method="hdr-gs"), "l1_dssim")
        out = method(features, exposure=0.5)
        assert calls == [6]
        expected_ldr = (weights @ method.crf(features.raw_colors + math.log(0.5))).reshape(12, 12, 3)
        torch.testing.assert_close(out.ldr, expected_ldr)
        torch.testing.assert_close(out.hdr, (weights @ torch.exp(features.raw_colors)).reshape(12, 12, 3))

    def test_exposure_changes_baseline_ldr(self):
        features, _, _ = fake_features()
        method = HdrGsBaseline(MethodConfig(method="hdr-gs"), "l1_dssim")
        assert not torch.allclose(method(features, 0.125).ldr, method(features, 32.0).ldr)

    def test_unit_exposure_loss(self):
        features, _, _ = fake_features()
        method = HdrNerfBaseline(MethodConfig(method="hdr-nerf"), "mse")
        terms = method.losses(method(features, 1.0), Targets(ldr=torch.rand(12, 12, 3), exposure=1.0), 0)
        unit = method.crf(torch.zeros(1, 3))
        torch.testing.assert_close(terms["unit_exposure"], 0.5 * ((unit - 0.5) ** 2).mean())

    def test_crf_warmup_ramps_learning_rate(self):
        method = HdrNerfBaseline(MethodConfig(method="hdr-nerf", options=HdrNerfOptions(crf_warmup_steps=100)), "mse")
        assert method.learning_rate("method", 0, 1.0) == pytest.approx(0.01)
        assert method.learning_rate("method", 500, 1.0) == 1.0
        assert (
            HdrGsBaseline(MethodConfig(method="hdr-gs"), "l1_dssim").learning_rate("method", 0, 1.0) == 1.0
        )  # HDR-GS's recipe has no warm-up
        assert "--crf-warmup-steps" not in HdrGsBaseline.own_flags()

    def test_huge_log_radiance_stays_finite(self):
        features, _, _ = fake_features()
        features.raw_colors.data.fill_(1e4)
        for cls, name in ((HdrNerfBaseline, "hdr-nerf"), (HdrGsBaseline, "hdr-gs")):
            out = cls(MethodConfig(method=name), "mse")(features, 1.0)
            assert torch.isfinite(out.hdr).all() and torch.isfinite(out.ldr).all()


class TestSaturatedPhotos:
    def test_above_one_where_the_photo_clipped_is_no_error(self):
        """A clipped pixel (1.0) only says the truth is >= 1; an unclipped one is compared as usual."""
        method = MonoHDR(MethodConfig(use_hdr_loss=False, use_h2l_loss=False), "mse")
        photo = torch.tensor([[1.0, 1.0, 1.0], [0.5, 0.5, 0.5]])
        ldr = torch.tensor([[1.7, 1.0, 0.8], [0.7, 0.5, 0.5]], requires_grad=True)
        loss = method.losses(MethodOutput(ldr=ldr, hdr=torch.ones(2, 3)), Targets(ldr=photo, exposure=1.0), 0)["ldr"]
        loss.backward()
        assert loss.item() == pytest.approx((0.2**2 + 0.2**2) / 6)
        assert ldr.grad[0, 0] == 0 and ldr.grad[0, 1] == 0, "at or above 1 on a clipped pixel: free"
        assert ldr.grad[0, 2] < 0 and ldr.grad[1, 0] > 0, "below a clipped pixel, or off an unclipped one: pulled"


def test_every_method_builds():
    assert method_names()[:6] == ["mono", "mlp-l2h", "mlp-h2l", "no-h2l", "hdr-nerf", "hdr-gs"]
    for name in method_names():
        assert build_method(MethodConfig(method=name), "mse").config.method == name
    with pytest.raises(RegistryError, match="no method named 'nope'; available: mono, mlp-l2h"):
        build_method(MethodConfig(method="nope"), "mse")


class TestMethodFlags:
    @pytest.mark.parametrize(
        ("name", "value", "accepted"),
        [
            ("hidden", 1, True),
            ("hidden", 0, False),
            ("unit_exposure_value", 0.999, True),
            ("unit_exposure_value", 1.0, False),
            ("unit_exposure_value", 0.0, False),
            ("unit_exposure_value", 1.5, False),
        ],
    )
    def test_rules_at_their_bounds(self, name, value, accepted):
        config = (
            MethodConfig(method="hdr-nerf", options=HdrNerfOptions(**{name: value}))
            if name.startswith("unit_")
            else MethodConfig(**{name: value})
        )
        if accepted:
            check_flags(config)
        else:
            with pytest.raises(FlagError, match=name.replace("_", "-")):
                check_flags(config)

    def test_converter_rate_given_or_the_official(self):
        assert build_method(MethodConfig(converter_lr=0.123), "mse").parameter_groups()[0]["lr"] == 0.123
        assert build_method(MethodConfig(), "mse").parameter_groups()[0]["lr"] == 5e-4  # both official codes
