"""Display curves, exposure and tone mapping, against hand-computed values and the HDR metric."""

import pytest
import torch

from mono_hdr_plugin.apps.display import aces_filmic, colour_depth, exposed_hdr, needs_render_at, to_display
from mono_hdr_plugin.core.colour import srgb_decode, srgb_encode
from mono_hdr_plugin.core.exposure import choose_reference
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.training.frames import ExposureModel
from mono_hdr_plugin.training.pipeline import Frame

MONO = ExposureModel(reference_exposure=2.0, display_scale=0.25, renders_any_exposure=False, ldr_exposures=(2.0,))
CRF = ExposureModel(reference_exposure=2.0, display_scale=0.25, renders_any_exposure=True)


def frame(exposure: float = 2.0, seed: int = 0) -> Frame:
    generator = torch.Generator().manual_seed(seed)
    hdr = torch.rand(6, 5, 3, generator=generator) * 20.0
    return Frame(ldr=torch.rand(6, 5, 3, generator=generator), hdr=hdr, depth=None, alpha=None, exposure=exposure)


class TestCurves:
    def test_srgb_known_values_and_inverse(self):
        # IEC 61966-2-1: 0.5 linear encodes to 0.73536; the linear segment below 0.0031308
        encoded = srgb_encode(torch.tensor([0.0, 0.002, 0.5, 1.0, 3.0]))
        torch.testing.assert_close(encoded, torch.tensor([0.0, 0.02584, 0.735357, 1.0, 1.0]), atol=2e-5, rtol=0)
        values = torch.linspace(0, 1, 101)
        torch.testing.assert_close(srgb_decode(srgb_encode(values)), values, atol=1e-6, rtol=0)

    def test_aces_fit_known_values(self):
        # x = 1: 2.54 / 3.16; x = 0.18 (mid grey) by hand; saturates to 1
        expected = torch.tensor(
            [0.0, 0.18 * (2.51 * 0.18 + 0.03) / (0.18 * (2.43 * 0.18 + 0.59) + 0.14), 2.54 / 3.16, 1.0]
        )
        torch.testing.assert_close(aces_filmic(torch.tensor([0.0, 0.18, 1.0, 1000.0])), expected, atol=1e-6, rtol=0)

    def test_reference_exposure_is_the_middle_training_exposure(self):
        assert choose_reference([32.0, 0.125, 2.0], [0.0] * 3) == 2
        assert choose_reference([0.5], [0.0]) == 0


class TestExposure:
    def test_hdr_scales_exactly_with_exposure(self):
        hdr = frame().hdr
        one = exposed_hdr(hdr, 0.5, MONO)
        assert torch.equal(exposed_hdr(hdr, 1.0, MONO), 2.0 * one)
        assert torch.equal(exposed_hdr(hdr, 0.25, MONO), 0.5 * one)
        torch.testing.assert_close(exposed_hdr(hdr, 2.0, MONO), 0.25 * hdr)  # k * hdr at the reference

    @pytest.mark.parametrize("output", ["hdr-srgb", "hdr-filmic", "hdr-mulaw"])
    def test_hdr_outputs_brighten_monotonically(self, output):
        shown = [to_display(frame(), output, 2.0 * 2.0**ev, MONO) for ev in range(-6, 7)]
        for darker, brighter in zip(shown, shown[1:]):
            assert (brighter >= darker - 1e-7).all()
        assert shown[-1].mean() > shown[0].mean()

    def test_mulaw_at_ev0_is_what_the_hdr_metric_sees(self):
        f = frame()
        torch.testing.assert_close(to_display(f, "hdr-mulaw", 2.0, MONO), normalise_hdr(f.hdr))

    def test_mono_ldr_is_its_branch_at_the_training_exposure_and_the_curve_elsewhere(self):
        f = frame()
        assert torch.equal(to_display(f, "ldr", 2.0, MONO), f.ldr)
        torch.testing.assert_close(to_display(f, "ldr", 8.0, MONO), srgb_encode(0.25 * f.hdr * 4.0))

    def test_camera_response_needs_a_render_at_the_shown_exposure(self):
        assert needs_render_at("ldr", CRF) and not needs_render_at("hdr-srgb", CRF) and not needs_render_at("ldr", MONO)
        assert torch.equal(to_display(frame(exposure=8.0), "ldr", 8.0, CRF), frame(exposure=8.0).ldr)
        with pytest.raises(ValueError, match="rendered at 2.0 s"):
            to_display(frame(exposure=2.0), "ldr", 8.0, CRF)

    def test_unknown_output_is_named(self):
        with pytest.raises(ValueError, match="'hdr-lin'"):
            to_display(frame(), "hdr-lin", 2.0, MONO)


class TestDepth:
    def test_near_is_warm_far_is_cool_empty_is_black(self):
        depth = torch.tensor([[1.0, 2.0, 3.0, 4.0]])
        alpha = torch.tensor([[1.0, 1.0, 1.0, 0.2]])
        image = colour_depth(depth, alpha)
        assert torch.equal(image[0, 3], torch.zeros(3))  # alpha below 0.5
        assert image[0, 0, 0] > image[0, 0, 2] and image[0, 2, 2] > image[0, 2, 0]  # turbo: red near, blue far

    def test_no_depth_is_black(self):
        f = frame()
        assert torch.equal(to_display(f, "depth", 2.0, MONO), torch.zeros_like(f.hdr))
