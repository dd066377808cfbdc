"""The radiance calibration: its estimator, its fit on training views, where it is stored, and the
display it sets. Scenes are built on the known render (known_render.py), whose HDR is a closed form,
so every expected scale is a number chosen here."""

import dataclasses
import math

import pytest
import torch
from known_render import KnownRenderConfig, camera_at, expected_render, zero_method

import mono_hdr_plugin.training.calibration as calibration_module
from mono_hdr_plugin.apps.display import to_display
from mono_hdr_plugin.core.calibration import (
    MIN_SAMPLES,
    WELL_EXPOSED,
    RadianceCalibration,
    fit_scale,
    median_log_ratio,
    well_exposed,
    well_exposed_channels,
)
from mono_hdr_plugin.core.colour import srgb_encode
from mono_hdr_plugin.core.exposure import ExposureConfig, build_view_exposures
from mono_hdr_plugin.core.metrics import aligning_scale, emitter_mask
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.methods.base import MethodConfig, MethodOutput, Targets, build_method
from mono_hdr_plugin.training.calibration import calibration_views, fit_radiance_calibration
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.frames import calibrate
from mono_hdr_plugin.training.pipeline import Pipeline
from mono_hdr_plugin.training.trained import load_trained_model
from mono_hdr_plugin.training.trainer import Trainer

TRUTH_FACTOR = 6.5
"""The ground truth is this times the known render's HDR."""
PHOTO_FACTOR = 0.4
"""The photos are srgb(this x the known HDR x t / reference exposure): what the display must fit."""


def model_hdr(camera) -> torch.Tensor:
    return torch.from_numpy(expected_render(camera, "mono")[1]).float()


def known_view(x: float, view_id: int, exposure: float, with_truth: bool, reference: float = 2.0) -> View:
    camera = camera_at(x)
    hdr = model_hdr(camera)
    photo = srgb_encode(PHOTO_FACTOR * hdr * exposure / reference).clamp(0.0, 1.0)
    return View(camera, photo, exposure, view_id, f"cam{view_id}", TRUTH_FACTOR * hdr if with_truth else None)


def known_scene(with_truth: bool = True, exposures=(2.0, 2.0, 2.0, 0.5, 8.0)) -> SceneData:
    train = [known_view(-1.0 + 0.6 * i, i, t, with_truth) for i, t in enumerate(exposures)]
    test = [known_view(0.3, 10, 2.0, with_truth)]
    return SceneData("known-calibration", train, test, torch.full((3,), -4.0), torch.full((3,), 4.0))


def known_pipeline(scene: SceneData) -> Pipeline:
    pipeline = Pipeline.create("known-render", KnownRenderConfig(), MethodConfig(method="mono"), scene.scene_info())
    zero_method(pipeline)
    return pipeline.eval()


class TestRadianceCalibration:
    def test_state_round_trip(self):
        calibration = RadianceCalibration(2.5, "ground_truth", 100, 7)
        assert RadianceCalibration.from_state(calibration.state()) == calibration
        assert not RadianceCalibration().fitted and calibration.fitted

    @pytest.mark.parametrize("scale", [0.0, -1.0, math.nan, math.inf])
    def test_a_scale_must_be_positive_and_finite(self, scale):
        with pytest.raises(ValueError, match="positive"):
            RadianceCalibration(scale, "ground_truth")

    def test_units_are_checked(self):
        with pytest.raises(ValueError, match="unknown radiance units 'nits'"):
            RadianceCalibration(1.0, "nits")  # type: ignore[arg-type]


class TestFitScale:
    def test_recovers_a_known_factor_ignoring_clipped_pixels(self):
        generator = torch.Generator().manual_seed(0)
        prediction = torch.rand(4000, 3, generator=generator) * 10 + 0.01
        target = 0.3 * prediction
        photo = srgb_encode(target).clamp(0, 1)  # a third of the pixels clip
        target[photo.amax(-1) >= 1.0] *= 50.0  # whatever the clipped pixels say must not count
        scale, count = fit_scale(target, prediction, photo)
        assert scale == pytest.approx(0.3, rel=1e-6)  # float32 ratios
        assert MIN_SAMPLES <= count < 4000 * 3

    def test_too_few_well_exposed_pixels_falls_back_to_every_pixel(self):
        prediction = torch.full((100, 3), 2.0)
        scale, count = fit_scale(4.0 * prediction, prediction, torch.ones(100, 3))
        assert (scale, count) == (pytest.approx(4.0), 300)

    def test_median_of_log_ratios_by_hand(self):
        # ratios 1, 2, 8, 16 (and a zero that does not count): median of the logs = log(sqrt(2 * 8)) = log 4
        target = torch.tensor([1.0, 2.0, 8.0, 16.0, 0.0])
        scale, count = median_log_ratio(target, torch.ones(5))
        assert (scale, count) == (pytest.approx(4.0), 4)

    def test_a_zero_or_non_finite_prediction_does_not_count(self):
        # a zero prediction would be an infinite ratio and move the median to 8
        prediction = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0, math.inf, math.nan])
        target = torch.tensor([1.0, 2.0, 8.0, 16.0, 5.0, 5.0, 5.0])
        assert median_log_ratio(target, prediction) == (pytest.approx(4.0), 4)

    def test_one_usable_entry_is_its_ratio_and_none_is_scale_one(self):
        assert median_log_ratio(torch.tensor([6.0, 0.0]), torch.tensor([2.0, 3.0])) == (pytest.approx(3.0), 1)
        assert median_log_ratio(torch.zeros(3), torch.ones(3)) == (1.0, 0)

    def test_an_exact_ratio_is_found_to_float64_accuracy(self):
        # powers of two times 4: exact in float32, so only the logs' precision is left (float32: ~1e-7)
        prediction = 2.0 ** torch.arange(-20, 20, dtype=torch.float32)
        scale, _ = median_log_ratio(4.0 * prediction, prediction)
        assert scale == pytest.approx(4.0, rel=1e-12)

    @pytest.mark.parametrize("exposed, expected", [(64, 2.0), (63, 10.0)])
    def test_the_well_exposed_fit_needs_64_usable_pixels(self, exposed, expected):
        """Well-exposed pixels say 2x, the clipped ones (more of them) 10x: the well-exposed median
        wins from exactly 64 usable pixels on; below, every pixel counts and 10x wins."""
        assert MIN_SAMPLES == 64
        clipped = 3 * 64
        photo = torch.cat([torch.full((exposed, 3), 0.5), torch.ones(clipped, 3)])
        prediction = torch.ones(exposed + clipped, 3)
        prediction[:exposed, 1:] = 0.0  # one usable channel per well-exposed pixel: exposed samples, not 3x
        target = torch.cat([torch.full((exposed, 3), 2.0), torch.full((clipped, 3), 10.0)])
        scale, count = fit_scale(target, prediction, photo)
        assert scale == pytest.approx(expected)
        assert count == (exposed if expected == 2.0 else exposed + 3 * clipped)


class TestWellExposed:
    def test_the_limits_themselves_are_not_well_exposed(self):
        low, high = WELL_EXPOSED
        photo = torch.tensor([[low, 0.5, high], [0.06, 0.5, 0.94]])
        assert well_exposed_channels(photo).tolist() == [[False, True, False], [True, True, True]]
        assert well_exposed(photo).tolist() == [False, True]

    def test_an_uncalibrated_model_keeps_its_scale(self):
        assert RadianceCalibration().state() == {
            "scale": 1.0,
            "units": "uncalibrated",
            "samples": 0,
            "step": None,
            "basis": "unknown",
        }


class TestHdrScores:
    def test_emitter_mask_leaves_out_the_brightest_tenth_of_a_percent(self):
        gt = torch.ones(40, 50, 3)  # 2000 pixels: 2 left out
        gt[3, 4, 1], gt[30, 40, 0], gt[0, 0] = 900.0, 500.0, 2.0
        keep = emitter_mask(gt)
        assert keep.sum() == 1998 and not keep[3, 4] and not keep[30, 40] and keep[0, 0]

    def test_aligning_scale_ignores_the_emitters(self):
        gt = torch.ones(40, 50, 3)
        gt[3, 4] = 1e4
        prediction = gt / 3.0
        prediction[3, 4] = 1.0  # a missed light: it must not pull the scale
        assert aligning_scale(prediction, gt) == pytest.approx(3.0)


class TestFitRadianceCalibration:
    def test_ground_truth_units_recover_the_truths_factor(self):
        scene = known_scene()
        calibration = fit_radiance_calibration(known_pipeline(scene), scene, step=5)
        assert calibration.units == "ground_truth" and calibration.step == 5
        assert calibration.scale == pytest.approx(TRUTH_FACTOR, rel=1e-5)

    def test_a_model_whose_hdr_is_off_by_a_factor_is_calibrated_back(self):
        scene = known_scene()
        pipeline = known_pipeline(scene)
        pipeline.calibration = RadianceCalibration(0.01, "ground_truth")  # a stale scale: the refit must undo it
        pipeline.calibration = fit_radiance_calibration(pipeline, scene)
        view = scene.test[0]
        torch.testing.assert_close(pipeline.render(view.camera, 2.0).hdr, view.hdr, rtol=1e-5, atol=1e-6)

    def test_without_ground_truth_the_units_are_the_exposure_times(self):
        scene = known_scene(with_truth=False)
        calibration = fit_radiance_calibration(known_pipeline(scene), scene)
        # photo = srgb(0.4 h t / 2): radiance x t through the response is 0.2 h t, so the scale is 0.2
        assert calibration.units == "exposure_seconds"
        assert calibration.scale == pytest.approx(PHOTO_FACTOR / 2.0, rel=5e-3)  # sRGB as a 256-entry table

    def test_a_ray_backbone_is_sampled_and_agrees(self):
        scene = known_scene()
        pipeline = known_pipeline(scene)
        pipeline.backbone.pixel_batch = 64  # as a NeRF: calibration renders sampled rays, not whole views
        pipeline.backbone.render_chunk = 50
        assert fit_radiance_calibration(pipeline, scene).scale == pytest.approx(TRUTH_FACTOR, rel=1e-5)

    def test_a_ray_backbone_renders_rays_per_view_and_a_whole_image_one_every_pixel(self, monkeypatch):
        monkeypatch.setattr(calibration_module, "RAYS_PER_VIEW", 40)
        scene = known_scene()
        pixels = scene.train[0].camera.width * scene.train[0].camera.height
        assert pixels > 40
        whole = fit_radiance_calibration(known_pipeline(scene), scene)
        pipeline = known_pipeline(scene)
        pipeline.backbone.pixel_batch = 64
        rays = fit_radiance_calibration(pipeline, scene)
        assert 5 * 40 * 3 * 0.5 < rays.samples <= 5 * 40 * 3  # 5 views, 40 rays, 3 channels; most usable
        assert whole.samples > 5 * pixels * 3 * 0.5

    def test_ray_samples_are_distinct_pixels_over_every_row_and_column(self):
        scene = known_scene()
        pipeline = known_pipeline(scene)
        pipeline.backbone.pixel_batch = 64
        view = scene.train[0]
        hdr, rows, cols = calibration_module._render_pixels(pipeline, view, torch.Generator().manual_seed(0))
        pixels = view.camera.width * view.camera.height
        assert len(set(zip(rows.tolist(), cols.tolist(), strict=True))) == len(rows) == min(pixels, 4096)
        assert set(cols.tolist()) == set(range(view.camera.width)) and set(rows.tolist()) == set(
            range(view.camera.height)
        )
        full = pipeline.render(view.camera, view.exposure).hdr
        torch.testing.assert_close(hdr, full[rows, cols])

    def test_a_view_that_is_not_square_is_sampled_at_its_own_pixels(self):
        def shorter(view: View) -> View:
            camera = dataclasses.replace(view.camera, height=view.camera.height - 6)
            hdr = model_hdr(camera)
            photo = srgb_encode(PHOTO_FACTOR * hdr * view.exposure / 2.0).clamp(0.0, 1.0)
            return dataclasses.replace(view, camera=camera, image=photo, hdr=TRUTH_FACTOR * hdr)

        square = known_scene()
        scene = dataclasses.replace(square, train=[shorter(v) for v in square.train], test=[shorter(square.test[0])])
        assert fit_radiance_calibration(known_pipeline(scene), scene).scale == pytest.approx(TRUTH_FACTOR, rel=1e-5)

    def test_per_view_exposures_are_the_models(self):
        """Learned exposures start at the views' times; with 4 of 5 views away from the reference
        exposure, reading them any other way moves the median."""
        scene = known_scene(with_truth=False, exposures=(0.5, 8.0, 2.0, 0.5, 8.0))
        exposures = build_view_exposures(ExposureConfig(learn_exposure=True, learn_white_balance="off"), scene)
        assert exposures is not None and exposures.reference_exposure == 2.0
        pipeline = Pipeline.create(
            "known-render", KnownRenderConfig(), MethodConfig(method="mono"), scene.scene_info(), exposures
        )
        zero_method(pipeline)
        calibration = fit_radiance_calibration(pipeline.eval(), scene)
        assert calibration.scale == pytest.approx(PHOTO_FACTOR / 2.0, rel=5e-3)

    @pytest.mark.parametrize(
        "views, expected",
        [(1, [0]), (2, [0, 1]), (3, [0, 1, 2]), (9, [0, 1, 2, 3, 5, 6, 7, 8]), (15, [0, 2, 4, 6, 8, 10, 12, 14])],
    )
    def test_views_are_spread_over_the_capture(self, views, expected):
        assert calibration_views(known_scene(exposures=(2.0,) * views)) == expected


class TestDisplayAtEv0:
    def test_the_hdr_display_at_a_training_view_is_its_photo(self):
        """At EV 0 (the reference exposure) and at another view's exposure, the HDR through the display
        curve is the dataset's photo: the display scale is fitted on the photos, not on the LDR branch."""
        scene = known_scene()
        pipeline = known_pipeline(scene)
        pipeline.calibration = fit_radiance_calibration(pipeline, scene)
        model = calibrate(pipeline, scene)
        assert model.reference_exposure == 2.0
        assert model.display_scale == pytest.approx(PHOTO_FACTOR / TRUTH_FACTOR, rel=1e-5)
        for view in (scene.train[0], scene.train[3]):  # EV 0, and two stops under
            frame = pipeline.render(view.camera, view.exposure)
            shown = to_display(frame, "hdr-srgb", view.exposure, model)
            assert (shown - view.image).abs().max() < 1e-4


class TestStoredWithTheModel:
    def test_checkpoint_round_trip_and_a_checkpoint_from_before(self, tmp_path):
        scene = known_scene()
        config = train_config_for(KnownRenderConfig)(
            backbone=KnownRenderConfig(), out=tmp_path / "run", quiet=True, max_steps=2, save_renders=False
        )
        trainer = Trainer(config, "known-render", scene)
        zero_method(trainer.pipeline)
        trainer.hdr_views = [False] * len(scene.train)  # no training signal: the converters stay zero
        trainer.train()
        saved = trainer.pipeline.calibration
        assert saved.fitted and saved.step == 2
        assert load_trained_model(trainer.checkpoint_path(), scene=scene).pipeline.calibration == saved

        payload = torch.load(trainer.checkpoint_path(), weights_only=True)
        del payload["pipeline"]["_extra_state"]  # as written before calibration existed
        torch.save(payload, trainer.checkpoint_path())
        refitted = load_trained_model(trainer.checkpoint_path(), scene=scene).pipeline.calibration
        # the loader refits with the run's --hdr-view-ratio (1:1: every view's truth), not the trainer's override
        assert refitted.units == "ground_truth" and refitted.scale == pytest.approx(TRUTH_FACTOR, rel=1e-5)


class TestScaleAnchor:
    def test_the_anchor_sees_the_level_that_l_hdr_cannot(self):
        method = build_method(MethodConfig(method="mono", hdr_scale_anchor=0.5), "mse")
        truth = torch.rand(8, 8, 3) * 4 + 0.1
        photo = torch.rand(8, 8, 3)

        def terms(prediction):
            return method.losses(MethodOutput(ldr=photo, hdr=prediction), Targets(photo, 1.0, truth), step=0)

        assert terms(truth)["hdr_anchor"] == 0.0
        doubled = terms(2.0 * truth)
        assert doubled["hdr"] == 0.0  # L_hdr divides each image by its own maximum: blind to the level
        assert doubled["hdr_anchor"] > 1e-3

    def test_off_by_default(self):
        method = build_method(MethodConfig(method="mono"), "mse")
        truth = torch.rand(8, 8, 3) + 0.1
        output = MethodOutput(ldr=torch.rand(8, 8, 3), hdr=2 * truth)
        assert "hdr_anchor" not in method.losses(output, Targets(output.ldr, 1.0, truth), step=0)
