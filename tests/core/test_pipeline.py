"""Pipeline: optimiser groups and their schedules, chunked rendering, eval mode, delegation."""

import math

import pytest
import torch
from known_render import KnownRenderBackbone, KnownRenderConfig, camera_at, expected_render, known_scene, zero_method

from mono_hdr_plugin.core.exposure import ViewExposures, srgb_response
from mono_hdr_plugin.methods.base import HdrMethod, MethodConfig, build_method
from mono_hdr_plugin.methods.hdr_nerf import HdrNerfOptions
from mono_hdr_plugin.training.pipeline import Pipeline


def pipeline_for(method: str = "mono", options: object = None, **method_settings) -> Pipeline:
    pipeline = Pipeline.create(
        "known-render",
        KnownRenderConfig(),
        MethodConfig(method=method, options=options, **method_settings),
        known_scene().scene_info(),
    )
    zero_method(pipeline)
    return pipeline


class TestParameterGroups:
    def test_groups_are_tagged_with_their_owner(self):
        pipeline = pipeline_for()
        groups = pipeline.parameter_groups()
        assert [(g["name"], g["owner"]) for g in groups] == [("backbone", "backbone"), ("method", "method")]
        assert groups[0]["params"] == [pipeline.backbone.unused]
        assert {id(p) for p in groups[1]["params"]} == {id(p) for p in pipeline.method.parameters()}
        assert groups[1]["lr"] == 5e-4

    def test_converter_rate_from_the_flag_else_from_the_backbone(self, monkeypatch):
        assert pipeline_for(converter_lr=0.123).parameter_groups()[1]["lr"] == 0.123
        monkeypatch.setattr(KnownRenderBackbone, "converter_lr", 0.0321)
        assert pipeline_for().parameter_groups()[1]["lr"] == 0.0321
        assert pipeline_for(converter_lr=0.123).parameter_groups()[1]["lr"] == 0.123

    def test_a_name_used_twice_is_refused(self, monkeypatch):
        pipeline = pipeline_for()
        monkeypatch.setattr(
            pipeline.method, "parameter_groups", lambda: [{"name": "backbone", "params": [], "lr": 1.0}]
        )
        with pytest.raises(ValueError, match="'backbone' is used by both the backbone 'known-render' and the method"):
            pipeline.parameter_groups()

    def test_learning_rate_follows_the_owner_schedule(self):
        pipeline = pipeline_for("hdr-nerf", HdrNerfOptions(crf_warmup_steps=10))
        groups = pipeline.parameter_groups()
        for group in groups:
            group["base_lr"] = 2.0
        backbone_group, method_group = groups
        assert pipeline.learning_rate(method_group, 0) == pytest.approx(0.2)  # CRF warm-up: (0 + 1) / 10
        assert pipeline.learning_rate(method_group, 4) == pytest.approx(1.0)
        assert pipeline.learning_rate(method_group, 50) == pytest.approx(2.0)
        assert pipeline.learning_rate(backbone_group, 0) == 2.0

    def test_run_length_reaches_the_backbone(self):
        pipeline = pipeline_for()
        pipeline.set_run_length(123)
        assert pipeline.backbone.max_steps == 123


class TestRender:
    @pytest.mark.parametrize("chunk", [None, 37, 256])
    @pytest.mark.parametrize("method", ["mono", "hdr-gs"])
    def test_whole_image_in_chunks_is_the_closed_form(self, monkeypatch, chunk, method):
        pipeline = pipeline_for(method)
        monkeypatch.setattr(pipeline.backbone, "render_chunk", chunk)
        calls = []
        render = pipeline.backbone.render_ldr_features
        monkeypatch.setattr(
            pipeline.backbone, "render_ldr_features", lambda camera: calls.append(camera.output_shape) or render(camera)
        )
        camera = camera_at(1.0)
        output = pipeline.render(camera, 0.5)
        ldr, hdr = expected_render(camera, method)
        assert output.ldr.shape == output.hdr.shape == (16, 16, 3)
        torch.testing.assert_close(output.ldr.double(), torch.from_numpy(ldr), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(output.hdr.double(), torch.from_numpy(hdr), rtol=1e-5, atol=1e-6)
        expected_calls = [(16, 16)] if chunk is None else [(min(chunk, 256 - i),) for i in range(0, 256, chunk)]
        assert calls == expected_calls
        assert not output.hdr.requires_grad

    def test_training_forward_returns_features_and_images(self):
        pipeline = pipeline_for()
        camera = camera_at(0.0)
        features, output = pipeline(camera, 0.5)
        ldr, hdr = expected_render(camera, "mono")
        torch.testing.assert_close(features.colors.reshape(16, 16, 3).double(), torch.from_numpy(ldr))
        torch.testing.assert_close(output.hdr.double(), torch.from_numpy(hdr), rtol=1e-5, atol=1e-6)
        assert output.ldr_from_hdr is not None


def one_stop_apart() -> ViewExposures:
    """Training view 1 one stop above the reference view 0 (0.5 s), nothing learned."""
    return ViewExposures(torch.tensor([0.0, math.log(2.0)]), 0, 0.5, srgb_response(), learn=False)


class TestViewExposures:
    """With per-view exposures, training view 1 (one stop above the reference view 0) renders at its own."""

    def pipeline(self, method: str) -> Pipeline:
        scene = known_scene()
        torch.manual_seed(0)  # untrained converters: images that depend on the exposure
        return Pipeline.create(
            "known-render", KnownRenderConfig(), MethodConfig(method=method), scene.scene_info(), one_stop_apart()
        )

    def test_methods_that_take_exposure_render_at_the_views_time(self):
        pipeline = self.pipeline("hdr-gs")
        features = pipeline.backbone.render_ldr_features(camera_at(0.5))
        output = pipeline._lift(features, 0.5, 1, training=True)
        torch.testing.assert_close(output.ldr, pipeline.method.render(features, 1.0).ldr)  # 0.5 s x 2
        assert not torch.allclose(output.ldr, pipeline.method.render(features, 0.25).ldr, atol=1e-4)

    def test_mono_brightens_its_images_by_the_views_ratio(self):
        pipeline = self.pipeline("mono")
        features = pipeline.backbone.render_ldr_features(camera_at(0.5))
        output = pipeline._lift(features, 0.5, 1, training=True)
        plain = pipeline.method.render(features, 0.5)
        brighter = lambda image: pipeline.exposures.brighten(image, torch.tensor(math.log(2.0)))  # noqa: E731 - the expectation, named
        torch.testing.assert_close(output.ldr, brighter(plain.ldr))
        torch.testing.assert_close(output.ldr_from_hdr, brighter(plain.ldr_from_hdr))
        assert not torch.allclose(output.ldr, plain.ldr, atol=1e-3)


class CoarseAndFineBackbone(KnownRenderBackbone):
    """Known renders with an auxiliary pass at half the brightness (as NeRF's coarse network)."""

    def render_ldr_features(self, camera):
        fine = super().render_ldr_features(camera)
        coarse = super().render_ldr_features(camera)
        coarse.colors = 0.5 * coarse.colors
        fine.auxiliary = [coarse]
        return fine


class TestAuxiliaryRenders:
    def pipeline(self, exposures=None) -> Pipeline:
        scene = known_scene()
        torch.manual_seed(0)
        return Pipeline(
            "known-render",
            CoarseAndFineBackbone(KnownRenderConfig(), scene.scene_info()),
            build_method(MethodConfig(), "mse"),
            exposures,
        )

    def test_training_forward_renders_the_auxiliary_pass_and_a_render_does_not(self):
        pipeline = self.pipeline()
        camera = camera_at(0.0)
        features, output = pipeline(camera, 0.5)
        torch.testing.assert_close(output.auxiliary_ldr[0], pipeline.method(features.auxiliary[0], 0.5).ldr)
        assert (
            len(output.auxiliary_ldr) == 1 and pipeline._lift(features, 0.5, None, training=False).auxiliary_ldr == []
        )

    def test_the_auxiliary_pass_is_brightened_like_the_image(self):
        exposures = one_stop_apart()
        pipeline = self.pipeline(exposures)
        features, output = pipeline(camera_at(0.0), 0.5, view=1)
        plain = pipeline.method(features.auxiliary[0], 0.5).ldr
        torch.testing.assert_close(output.auxiliary_ldr[0], exposures.brighten(plain, torch.tensor(math.log(2.0))))


class SplatDepthBackbone(KnownRenderBackbone):
    """Known renders whose depth costs an extra pass (as 3DGS's): extras "render_depth", no "depth"."""

    def render_ldr_features(self, camera):
        features = super().render_ldr_features(camera)
        features.extras["render_depth"] = lambda: torch.full(camera.output_shape, 2.5)
        return features


class TestDepth:
    def test_depth_only_when_asked_where_it_costs_a_pass(self):
        scene = known_scene()
        pipeline = Pipeline(
            "known-render",
            SplatDepthBackbone(KnownRenderConfig(), scene.scene_info()),
            build_method(MethodConfig(), "mse"),
        )
        with pipeline.evaluating():
            assert pipeline.render(camera_at(0.0), 0.5).depth is None
            depth = pipeline.render(camera_at(0.0), 0.5, with_depth=True).depth
        assert depth.shape == (16, 16) and torch.all(depth == 2.5)


class TestModes:
    def test_evaluating_restores_the_previous_mode(self):
        pipeline = pipeline_for()
        assert pipeline.training
        with pipeline.evaluating() as same:
            assert same is pipeline and not pipeline.training and not pipeline.method.training
        assert pipeline.training and pipeline.backbone.training
        pipeline.eval()
        with pipeline.evaluating():
            assert not pipeline.training
        assert not pipeline.training

    def test_mode_restored_after_an_error(self):
        pipeline = pipeline_for()
        with pytest.raises(RuntimeError), pipeline.evaluating():
            raise RuntimeError("render failed")
        assert pipeline.training


class RecordingBackbone(KnownRenderBackbone):
    def after_step(self, step, features, optimizer):
        self.seen = (step, features, optimizer)


def test_after_step_and_losses_are_delegated():
    scene = known_scene()
    pipeline = Pipeline(
        "known-render", RecordingBackbone(KnownRenderConfig(), scene.scene_info()), HdrMethod(MethodConfig(), "mse")
    )
    sentinel = object()
    pipeline.after_step(7, "features", sentinel)
    assert pipeline.backbone.seen == (7, "features", sentinel)
    assert pipeline.method_name == "mono" and pipeline.backbone_name == "known-render"
