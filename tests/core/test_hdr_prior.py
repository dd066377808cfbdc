"""HDR where no HDR view exists: L_prior, what a run says its HDR rests on, a calibration that never reads
ground truth training was not given, and the scores of an HDR against its own photos. Every expected
value is chosen here (closed forms on the known render, sRGB by its formula)."""

import math

import numpy as np
import pytest
import torch
from known_render import KnownRenderConfig
from test_calibration import PHOTO_FACTOR, known_pipeline, known_scene

from mono_hdr_plugin.apps.studio.dataset import capture_response
from mono_hdr_plugin.apps.studio.scenes import SCENES
from mono_hdr_plugin.core.exposure import ExposureConfig, build_view_exposures, srgb_response
from mono_hdr_plugin.core.losses import log_ratio_loss
from mono_hdr_plugin.core.metrics import (
    OWN_LDR_PREFIX,
    clipped_split_metrics,
    radiance_consistency,
    radiance_warnings,
)
from mono_hdr_plugin.methods.base import HDR_PRIOR_WEIGHT, MethodConfig, MethodOutput, Targets, build_method
from mono_hdr_plugin.training.calibration import fit_radiance_calibration
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.hdr_prior import hdr_basis, prior_radiance
from mono_hdr_plugin.training.trainer import Trainer

SRGB = torch.as_tensor(srgb_response(), dtype=torch.float32)
SRGB_HALF = ((0.5 + 0.055) / 1.055) ** 2.4
"""sRGB code value 0.5 in linear light (IEC 61966-2-1)."""


class TestLogRatioLoss:
    def test_a_factor_costs_its_log(self):
        target = torch.rand(100, 3) + 0.5
        assert log_ratio_loss(2.0 * target, target).item() == pytest.approx(math.log(2.0), rel=1e-3)
        assert log_ratio_loss(target / 4.0, target).item() == pytest.approx(math.log(4.0), rel=1e-3)

    def test_a_dead_channel_is_finite(self):
        target = torch.rand(10, 3) + 0.5
        loss = log_ratio_loss(torch.zeros(10, 3, requires_grad=True), target)
        assert torch.isfinite(loss) and loss.item() > 5.0


class TestPriorRadiance:
    def test_linearises_and_divides_by_the_relative_exposure(self):
        photo = torch.tensor([[0.5, 0.0, 1.0]])
        torch.testing.assert_close(prior_radiance(photo, SRGB, 2.0), torch.tensor([[SRGB_HALF / 2, 0.0, 0.5]]))


class TestPriorTerm:
    def test_only_well_exposed_channels_count(self):
        method = build_method(MethodConfig(method="mono", hdr_prior_weight=0.5), "mse")
        photo = torch.full((4, 4, 3), 0.5)
        photo[0, :, 0] = 1.0  # clipped red: whatever the radiance target says there must not count
        radiance = torch.full((4, 4, 3), 0.2)
        radiance[0, :, 0] = 1e6
        output = MethodOutput(ldr=photo, hdr=3.0 * torch.full((4, 4, 3), 0.2))
        terms = method.losses(output, Targets(photo, 1.0, radiance=radiance), step=0)
        assert terms["hdr_prior"].item() == pytest.approx(0.5 * math.log(3.0), rel=1e-3)

    def test_no_term_with_ground_truth_or_weight_zero(self):
        photo = torch.full((4, 4, 3), 0.5)
        output = MethodOutput(ldr=photo, hdr=torch.ones(4, 4, 3))
        with_prior = build_method(MethodConfig(method="mono", hdr_prior_weight=0.5), "mse")
        assert "hdr_prior" not in with_prior.losses(output, Targets(photo, 1.0, hdr=torch.ones(4, 4, 3)), step=0)
        off = build_method(MethodConfig(method="mono", hdr_prior_weight=0.0), "mse")
        assert "hdr_prior" not in off.losses(output, Targets(photo, 1.0, radiance=torch.ones(4, 4, 3)), step=0)


def trainer_for(tmp_path, ratio: str, exposures=(2.0, 2.0, 2.0, 0.5, 8.0)) -> Trainer:
    config = train_config_for(KnownRenderConfig)(
        backbone=KnownRenderConfig(), out=tmp_path / "run", quiet=True, max_steps=2, hdr_view_ratio=ratio
    )
    return Trainer(config, "known-render", known_scene(exposures=exposures))


class TestTrainerPrior:
    def test_without_hdr_views_the_prior_is_on_and_targets_the_photos_radiance(self, tmp_path):
        trainer = trainer_for(tmp_path, "1:0")
        assert trainer.method.config.hdr_prior_weight == HDR_PRIOR_WEIGHT
        for index in (0, 3, 4):  # 2 s (the reference view), 0.5 s and 8 s
            view = trainer.scene.train[index]
            _, targets = trainer._batch(view, index)
            assert targets.hdr is None
            relative = view.exposure / 2.0
            expected = torch.from_numpy(np.interp(view.image.numpy(), np.linspace(0, 1, 256), SRGB[:, 0].numpy()))
            torch.testing.assert_close(targets.radiance, expected.float() / relative, rtol=1e-5, atol=1e-7)

    def test_with_hdr_views_it_is_off(self, tmp_path):
        trainer = trainer_for(tmp_path, "2:1")
        assert trainer.method.config.hdr_prior_weight == 0.0 and trainer.prior_response is None
        index = trainer.hdr_views.index(False)  # a view without HDR supervision gets no prior either
        assert trainer._batch(trainer.scene.train[index], index)[1].radiance is None


class TestHdrBasis:
    def test_names_what_the_hdr_rests_on(self):
        scene = known_scene()
        assert hdr_basis(scene, None, None) == "5 HDR ground-truth views"
        assert hdr_basis(scene, [True, False, False, False, False], None) == "1 HDR ground-truth view"
        without = hdr_basis(scene, [False] * 5, None)
        assert without.startswith("the sRGB response") and "no HDR views" in without
        assert "exposure ratios across views (0.5-8 s)" in without
        assert "exposure ratios" not in hdr_basis(known_scene(exposures=(2.0,) * 5), [False] * 5, None)

    def test_two_exposures_are_ratios_and_float_noise_is_one_exposure(self):
        two = hdr_basis(known_scene(exposures=(2.0, 2.0, 2.0, 2.0, 8.0)), [False] * 5, None)
        assert two.endswith("; exposure ratios across views (2-8 s)")
        noise = (2.0, 2.0, 2.0, 2.0, 2.0 * (1 + 3e-7))  # an exposure time written with fewer digits
        assert "exposure ratios" not in hdr_basis(known_scene(exposures=noise), [False] * 5, None)

    @pytest.mark.parametrize("unknown, start", [(False, "EXIF times as a start"), (True, "the capture knows no times")])
    def test_learned_exposures_and_white_balance_are_named(self, unknown, start):
        scene = known_scene(exposures=(2.0,) * 5)
        if unknown:
            scene.metadata["unknown_exposures"] = [view.name for view in scene.train]
        exposures = build_view_exposures(ExposureConfig(learn_exposure=True, learn_white_balance="off"), scene)
        basis = hdr_basis(scene, [False] * 5, exposures)
        assert basis.endswith(f"; exposure ratios across views, learned ({start})")
        balanced = build_view_exposures(ExposureConfig(learn_exposure=True, learn_white_balance="on"), scene)
        assert hdr_basis(scene, [False] * 5, balanced) == basis + (
            "; white balance per view, learned (the HDR keeps the photos' mean balance)"
        )

    def test_a_view_selection_of_another_length_is_refused(self):
        with pytest.raises(ValueError):
            hdr_basis(known_scene(), [True, False], None)

    def test_a_fitted_response_is_named(self):
        scene = known_scene(with_truth=False)
        scene.metadata.update(camera_response=srgb_response().tolist(), camera_response_source="recovered from 3 sets")
        assert hdr_basis(scene, None, None).startswith("the camera response recovered from 3 sets, no HDR views")


class TestCalibrationNeverReadsUnusedTruth:
    def test_a_run_without_hdr_views_is_calibrated_in_exposure_units(self):
        scene = known_scene()  # every view has ground truth, 6.5x the render: training was not given it
        calibration = fit_radiance_calibration(known_pipeline(scene), scene, hdr_views=[False] * 5)
        assert calibration.units == "exposure_seconds"
        assert calibration.scale == pytest.approx(PHOTO_FACTOR / 2.0, rel=5e-3)  # not 6.5
        assert "no HDR views" in calibration.basis


class TestRadianceConsistency:
    def scene(self):
        linear = torch.rand(50, 40, 3, generator=torch.Generator().manual_seed(1)) * 0.9 + 0.02
        photo = (torch.round(linear ** (1 / 2.2) * 255) / 255).clamp(0, 1)  # quantised: many ties
        return photo, linear

    def test_radiance_scores_one_a_square_root_a_half(self):
        photo, linear = self.scene()
        scores = radiance_consistency(7.0 * linear, linear, photo)
        assert all(scores[f"hdr_rank_correlation_{c}"] == pytest.approx(1.0) for c in "rgb")
        assert all(scores[f"hdr_log_slope_{c}"] == pytest.approx(1.0) for c in "rgb")
        root = radiance_consistency(linear.sqrt(), linear, photo)
        assert root["hdr_log_slope_g"] == pytest.approx(0.5)
        assert radiance_warnings(scores) == []
        assert len(radiance_warnings(root)) == 3 and "power 0.500" in radiance_warnings(root)[0]
        assert "the test photos" in radiance_warnings(root)[0]

    def test_an_inverted_channel_is_found(self):
        photo, linear = self.scene()
        hdr = linear.clone()
        hdr[..., 2] = 1.0 / linear[..., 2]
        scores = radiance_consistency(hdr, linear, photo)
        assert scores["hdr_rank_correlation_b"] == pytest.approx(-1.0) and scores["hdr_rank_correlation_r"] > 0.999
        warnings = radiance_warnings(scores)
        assert any("b channel has rank correlation -1.000" in w for w in warnings)

    def test_a_constant_channel_follows_nothing(self):
        photo, linear = self.scene()
        hdr = linear.clone()
        hdr[..., 1] = 0.3  # a dead converter: one value whatever the photo
        scores = radiance_consistency(hdr, linear, photo)
        assert scores["hdr_rank_correlation_g"] == 0.0 and scores["hdr_log_slope_g"] == 0.0
        assert any("g channel has rank correlation 0.000" in w for w in radiance_warnings(scores))

    def test_a_model_that_misses_the_photo_is_told_from_an_hdr_that_is_not_radiance(self):
        photo, linear = self.scene()
        # the model renders a blurred photo and its HDR is exactly the radiance of that render
        blurred = (linear + torch.roll(linear, 1, 0) + torch.roll(linear, 1, 1)) / 3
        render = (torch.round(blurred ** (1 / 2.2) * 255) / 255).clamp(0, 1)
        scores = radiance_consistency(blurred, linear, photo)
        scores |= radiance_consistency(blurred, blurred, render, OWN_LDR_PREFIX)
        assert scores["hdr_rank_correlation_r"] < 0.9 and scores["hdr_log_slope_r"] < 0.9  # the regressor's error
        assert scores["hdr_own_ldr_rank_correlation_r"] == pytest.approx(1.0)
        assert scores["hdr_own_ldr_log_slope_r"] == pytest.approx(1.0)
        warnings = radiance_warnings(scores)
        assert len(warnings) == 6 and all("the model misses the photos" in w for w in warnings)
        # an HDR that is the square root of its own render's radiance is the HDR's fault
        scores |= radiance_consistency(blurred.sqrt(), blurred, render, OWN_LDR_PREFIX)
        warnings = radiance_warnings(scores)
        assert not any("the model misses the photos" in w for w in warnings)
        assert (
            sum("power 0.500 (radiance: 1, accepted 0.9-1.1) of the model's own LDR renders" in w for w in warnings)
            == 3
        )

    def test_clipped_and_dark_values_do_not_count(self):
        photo, linear = self.scene()
        hdr = linear.clone()
        photo[:25] = 1.0  # half the image clips: there the HDR may be anything
        hdr[:25] = torch.rand(25, 40, 3)
        assert radiance_consistency(hdr, linear, photo)["hdr_rank_correlation_r"] == pytest.approx(1.0)
        nothing = radiance_consistency(hdr, linear, torch.ones_like(photo))
        assert all(math.isnan(value) for value in nothing.values())


class TestClippedSplit:
    def test_scores_clipped_and_unclipped_pixels_apart(self):
        gt = torch.full((10, 10, 3), 0.1)
        gt[:2] = 10.0
        photo = torch.full((10, 10, 3), 0.5)
        photo[:2, :, 1] = 1.0  # a pixel counts as clipped when any channel is
        pred = gt.clone()
        pred[:2] = 1.0  # the extrapolation stopped at the clip level
        scores = clipped_split_metrics(pred, gt, photo)
        assert scores["hdr_psnr_unclipped"] == math.inf and scores["clipped_fraction"] == pytest.approx(0.2)
        assert 0 < scores["hdr_psnr_clipped"] < 20


class TestStudioResponse:
    def test_the_studio_declares_its_capture_curve(self):
        glossy = capture_response(SCENES["glossy"])  # a gamma 2.2 camera
        assert glossy.shape == (256, 3) and glossy[128, 1] == pytest.approx((128 / 255) ** 2.2, rel=1e-5)
        demo = capture_response(SCENES["demo"])  # sRGB
        assert demo[128, 0] == pytest.approx(((128 / 255 + 0.055) / 1.055) ** 2.4, rel=1e-5)
