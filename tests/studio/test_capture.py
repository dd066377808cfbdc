"""Capture simulator: each stage, its inverse, and the declared-effects rule."""

from unittest import mock

import numpy as np
import pytest

from mono_hdr_plugin.apps.studio import capture as capture_module
from mono_hdr_plugin.apps.studio.capture import (
    INVERSES,
    PHYSICAL_ORDER,
    STAGES,
    CaptureContext,
    CaptureSettings,
    capture,
    inverse_response_curve,
    linearise,
    response_curve,
    validate_effects,
)

CONTEXT = CaptureContext(exposure=2.0, seed=3)


@pytest.fixture
def radiance():
    return np.random.default_rng(0).random((8, 9, 3), dtype=np.float32) * 0.4


class TestInvertibleStages:
    @pytest.mark.parametrize("name", sorted(INVERSES))
    def test_round_trip(self, name, radiance):
        settings = CaptureSettings(gain=1.7, offset=0.01, vignette=0.4, white_balance=(1.2, 1.0, 0.8))
        forward = STAGES[name](radiance, settings, CONTEXT)
        assert not np.allclose(forward, radiance)  # the stage does something
        np.testing.assert_allclose(INVERSES[name](forward, settings, CONTEXT), radiance, rtol=1e-4, atol=1e-6)

    def test_exposure_scales_linearly(self, radiance):
        assert np.allclose(STAGES["exposure"](radiance, CaptureSettings(), CONTEXT), 2.0 * radiance)

    def test_vignette_is_one_at_centre_and_darker_at_corners(self):
        image = np.ones((11, 11, 3), np.float32)
        out = STAGES["vignette"](image, CaptureSettings(vignette=0.4), CONTEXT)
        assert out[5, 5, 0] == pytest.approx(1.0, abs=0.01) and out[0, 0, 0] < 0.75


class TestResponseCurves:
    @pytest.mark.parametrize("crf", ["srgb", "bt709", "gamma", "film"])
    def test_endpoints_monotonic_and_inverse(self, crf):
        settings = CaptureSettings(crf=crf)
        x = np.linspace(0, 1, 257, dtype=np.float32)
        y = response_curve(x, settings)
        assert y[0] == pytest.approx(0, abs=1e-6) and y[-1] == pytest.approx(1, abs=1e-5)
        assert np.all(np.diff(y) > 0)
        np.testing.assert_allclose(inverse_response_curve(y, settings), x, atol=2e-5)

    def test_srgb_matches_colour_science(self):
        import colour

        x = np.array([0.001, 0.18, 0.5])
        assert np.allclose(response_curve(x, CaptureSettings(crf="srgb")), colour.cctf_encoding(x, function="sRGB"))

    def test_negative_input_reads_black(self):
        assert response_curve(np.array([-0.5]), CaptureSettings(crf="gamma"))[0] == 0

    def test_unknown_curve_is_an_error(self):
        with pytest.raises(ValueError, match="crf must be one of"):
            CaptureSettings(crf="log")


class TestNoise:
    def test_seeded_and_reproducible(self, radiance):
        settings = CaptureSettings()
        first = STAGES["noise"](radiance, settings, CONTEXT)
        assert np.array_equal(first, STAGES["noise"](radiance, settings, CONTEXT))
        other = STAGES["noise"](radiance, settings, CaptureContext(exposure=2.0, seed=4))
        assert not np.array_equal(first, other)

    def test_poisson_gaussian_statistics(self):
        settings = CaptureSettings(full_well=500.0, read_noise=0.01)
        flat = np.full((200, 200, 3), 0.3, np.float32)
        noisy = STAGES["noise"](flat, settings, CONTEXT)
        assert noisy.mean() == pytest.approx(0.3, rel=0.01)
        expected_variance = 0.3 / settings.full_well + settings.read_noise**2
        assert noisy.var() == pytest.approx(expected_variance, rel=0.05)


class TestClipAndQuantize:
    def test_clip_range(self):
        out = STAGES["clip"](np.array([-1.0, 0.5, 3.0], np.float32), CaptureSettings(), CONTEXT)
        assert out.tolist() == [0.0, 0.5, 1.0]

    @pytest.mark.parametrize("bits", [8, 10, 12, 16])
    def test_quantize_levels_and_idempotent(self, bits, radiance):
        settings = CaptureSettings(bits=bits)
        once = STAGES["quantize"](radiance, settings, CONTEXT)
        levels = once * (2**bits - 1)
        assert np.allclose(levels, np.round(levels), atol=1e-2)
        assert np.abs(once - radiance).max() <= 0.5 / (2**bits - 1) + 1e-7
        assert np.array_equal(STAGES["quantize"](once, settings, CONTEXT), once)

    def test_bad_bit_depth(self):
        with pytest.raises(ValueError, match="bits must be one of"):
            CaptureSettings(bits=9)


class TestDeclaredEffects:
    def test_undeclared_stages_are_never_called(self, radiance):
        declared = ("exposure", "crf", "clip", "quantize")
        spies = {name: mock.Mock(side_effect=stage) for name, stage in STAGES.items()}
        with mock.patch.dict(capture_module.STAGES, spies):
            capture(radiance, 2.0, declared)
        for name, spy in spies.items():
            assert spy.call_count == (1 if name in declared else 0), name

    @pytest.mark.parametrize("extra", [e for e in PHYSICAL_ORDER if e not in ("exposure", "quantize")])
    def test_output_is_exactly_the_declared_stages(self, extra, radiance):
        base = ("exposure", "quantize")
        settings = CaptureSettings(gain=1.5, offset=0.02, vignette=0.3, white_balance=(1.1, 1.0, 0.9), saturation=0.8)
        without = capture(radiance, 2.0, base, settings)
        expected = STAGES["quantize"](
            STAGES["exposure"](radiance, settings, CaptureContext(2.0)), settings, CaptureContext(2.0)
        )
        assert np.array_equal(without, expected)  # bit-identical: nothing undeclared ran
        assert not np.array_equal(capture(radiance, 2.0, base + (extra,), settings, seed=1), without)

    def test_stages_run_in_physical_order_whatever_the_declared_order(self, radiance):
        calls = []
        spies = {name: mock.Mock(side_effect=lambda im, s, c, n=name: calls.append(n) or im) for name in STAGES}
        with mock.patch.dict(capture_module.STAGES, spies):
            capture(radiance, 1.0, ("quantize", "crf", "exposure", "noise"))
        assert calls == ["exposure", "noise", "crf", "quantize"]

    def test_unknown_effect(self):
        with pytest.raises(ValueError, match="unknown capture effect.*bloom"):
            validate_effects(("exposure", "bloom"))

    def test_linearise_inverts_a_noise_free_capture(self, radiance):
        effects = ("exposure", "gain", "offset", "vignette", "white_balance", "crf")
        settings = CaptureSettings(crf="film", gain=1.2, offset=0.01, white_balance=(1.1, 1.0, 0.9))
        photo = capture(radiance, 0.5, effects, settings)
        np.testing.assert_allclose(linearise(photo, 0.5, effects, settings), radiance, rtol=1e-3, atol=1e-5)
