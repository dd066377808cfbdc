"""Exposure per view: the response table, the brightness term, and learning known exposure ratios."""

import json
import math

import colour
import numpy as np
import pytest
import torch
from helpers import quiet_config

from mono_hdr_plugin.core.exposure import (
    ExposureConfig,
    ViewExposures,
    build_view_exposures,
    choose_reference,
    decode,
    encode,
    fit_log_relative,
    photometric_log_exposures,
    srgb_response,
)
from mono_hdr_plugin.training.frames import calibrate

SRGB = torch.from_numpy(srgb_response()).float()


def random_image(seed: int, shape=(8, 8, 3)) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) * 0.8 + 0.1


class TestResponseTable:
    def test_decode_matches_srgb_between_and_at_the_samples(self):
        code = torch.linspace(0, 1, 1001)[:, None].expand(-1, 3)
        expected = colour.cctf_decoding(code.numpy().astype(np.float64), function="sRGB")
        np.testing.assert_allclose(decode(code, SRGB).numpy(), expected, atol=2e-4)

    def test_encode_inverts_decode(self):
        code = torch.rand(200, 3, generator=torch.Generator().manual_seed(0))
        np.testing.assert_allclose(encode(decode(code, SRGB), SRGB).numpy(), code.numpy(), atol=1e-5)

    def test_encode_clips_at_white(self):
        assert encode(torch.full((2, 3), 5.0), SRGB).max() == 1.0

    def test_gradients_float64(self):
        response = SRGB.double()
        code = torch.tensor(
            [[0.2013, 0.5021, 0.7007], [0.3109, 0.4417, 0.9031]], dtype=torch.float64, requires_grad=True
        )  # away from the table knots (k / 255), where slopes change
        linear = torch.tensor([[0.05, 0.2, 0.4]], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda x: decode(x, response), (code,))
        assert torch.autograd.gradcheck(lambda x: encode(x, response), (linear,))


def exposures_module(initial_log, reference=0, learn=True):
    return ViewExposures(torch.tensor(initial_log), reference, 1.0, srgb_response(), learn=learn)


class TestBrightness:
    def test_two_stops_brighter_is_four_times_the_light(self):
        ldr = random_image(0) * 0.4
        brighter = exposures_module([0.0]).brighten(ldr, torch.tensor(math.log(4.0)))
        np.testing.assert_allclose(decode(brighter, SRGB).numpy(), 4 * decode(ldr, SRGB).numpy(), rtol=2e-3, atol=1e-5)

    def test_reference_view_stays_put(self):
        module = exposures_module([0.0, 0.5])
        with torch.no_grad():
            for correction in module.correction:
                correction.fill_(0.3)
        assert module.log_relative(0) == 0.0
        assert module.log_relative(1).item() == pytest.approx(0.8)

    def test_novel_exposure_relative_to_the_reference(self):
        module = ViewExposures(torch.zeros(2), 0, 0.01, srgb_response(), learn=False)
        assert module.log_relative(exposure=0.04).item() == pytest.approx(math.log(4))

    def test_fit_finds_the_brightness_of_a_photo(self):
        module = exposures_module([0.0])
        ldr = random_image(1) * 0.5
        photo = module.brighten(ldr, torch.tensor(0.7))
        assert fit_log_relative(ldr, photo, SRGB).item() == pytest.approx(0.7, abs=1e-3)


class TestLearning:
    def test_recovers_known_ratios(self):
        """Views of one canonical image at known brightness ratios; the model learns the image and
        the ratios from the photos alone, the first view fixed."""
        true_log = torch.tensor([0.0, 0.6, -0.4, 1.1, -0.9, 0.25])
        canonical = random_image(2) * 0.6
        module = exposures_module([0.0] * len(true_log))
        photos = [module.brighten(canonical, value).detach() for value in true_log]
        image_logits = torch.zeros_like(canonical, requires_grad=True)
        optimiser = torch.optim.Adam(
            [{"params": [image_logits], "lr": 0.1}, {"params": list(module.correction), "lr": 0.05}]
        )
        decay = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma=0.995)  # lr / 20 by the end
        for step in range(600):
            view = step % len(photos)
            rendered = module.brighten(torch.sigmoid(image_logits), module.log_relative(view))
            loss = torch.abs(rendered - photos[view]).mean()
            optimiser.zero_grad(set_to_none=True)  # as the trainer: Adam skips the views not rendered
            loss.backward()
            optimiser.step()
            decay.step()
        np.testing.assert_allclose(module.relative_exposures().numpy(), torch.exp(true_log).numpy(), rtol=0.01)

    def test_frozen_when_not_learning(self):
        module = exposures_module([0.0, 0.3], learn=False)
        assert module.parameter_groups() == [] and not module.learned
        np.testing.assert_allclose(module.relative_exposures().numpy(), np.exp([0.0, 0.3]), rtol=1e-6)

    def test_state_round_trip(self):
        module = exposures_module([0.0, 0.3, -0.2], reference=1)
        with torch.no_grad():
            for correction, value in zip(module.correction, (0.1, 0.0, 0.05)):
                correction.fill_(value)
        loaded = ViewExposures.from_state_dict({f"exposures.{k}": v for k, v in module.state_dict().items()})
        loaded.load_state_dict(module.state_dict())
        torch.testing.assert_close(loaded.relative_exposures(), module.relative_exposures())


class FakeView:
    def __init__(self, exposure, name, brightness=0.5):
        self.exposure, self.name, self.image = exposure, name, torch.full((2, 2, 3), brightness)


class FakeScene:
    def __init__(self, exposures, unknown=()):
        self.train = [FakeView(e, f"{i:03d}_0.png", 0.1 * i) for i, e in enumerate(exposures)]
        self.metadata = {"unknown_exposures": list(unknown)}
        self.points = None


class TestPhotometricStart:
    def test_measures_the_ratios_of_a_lit_plane(self):
        """A textured plane photographed from four places at known exposures: the points' brightness
        across the photos gives the ratios."""
        from mono_hdr_plugin.core.cameras import Camera, look_at
        from mono_hdr_plugin.data.dataset import View

        rng = np.random.default_rng(0)
        points = np.concatenate([rng.uniform(-1, 1, (400, 2)), np.zeros((400, 1))], 1)
        albedo = rng.uniform(0.05, 0.3, 400)
        true_log = np.array([0.0, 0.5, -0.4, 0.9])
        views = []
        for index, value in enumerate(true_log):
            eye = torch.tensor([0.3 * index - 0.45, -0.2, 3.0])
            camera = Camera(c2w=look_at(eye, torch.zeros(3)), fx=60.0, fy=60.0, cx=32.0, cy=32.0, width=64, height=64)
            image = np.zeros((64, 64, 3))
            local = (points - eye.numpy()) @ camera.c2w[:3, :3].double().numpy()
            cols = np.floor(60 * local[:, 0] / local[:, 2] + 32).astype(int)
            rows = np.floor(60 * local[:, 1] / local[:, 2] + 32).astype(int)
            linear = np.clip(albedo * math.exp(value), 0, 1)
            image[rows, cols] = colour.cctf_encoding(linear, function="sRGB")[:, None]
            views.append(View(camera=camera, image=torch.from_numpy(image).float(), exposure=1.0, view_id=index))
        measured = photometric_log_exposures(views, torch.from_numpy(points), srgb_response(), reference=0)
        np.testing.assert_allclose(measured, true_log, atol=0.02)


class TestBuild:
    def test_one_known_exposure_needs_no_model(self):
        assert build_view_exposures(ExposureConfig(), FakeScene([0.5, 0.5, 0.5])) is None

    def test_auto_exposure_with_exif_is_fixed(self):
        module = build_view_exposures(ExposureConfig(), FakeScene([1 / 60, 1 / 30, 1 / 125]))
        assert not module.learned and module.reference == 0  # the median exposure
        np.testing.assert_allclose(module.relative_exposures().numpy(), [1.0, 2.0, 60 / 125], rtol=1e-6)

    def test_unknown_exposures_are_learned(self):
        scene = FakeScene([1.0, 1.0, 1.0], unknown=["000_0.png", "001_0.png", "002_0.png"])
        module = build_view_exposures(ExposureConfig(), scene)
        assert module.learned and not module.known and module.report()["reference_exposure"] is None
        assert build_view_exposures(ExposureConfig(learn_exposure=False), scene) is None

    def test_flag_turns_learning_on(self):
        module = build_view_exposures(ExposureConfig(learn_exposure=True, exposure_lr=0.1), FakeScene([0.5, 0.5]))
        assert module.learned and module.parameter_groups()[0]["lr"] == 0.1

    def test_reference_is_the_median(self):
        assert choose_reference([4.0, 1.0, 2.0, 8.0, 0.5], [0.0] * 5) == 2
        assert choose_reference([1.0, 1.0, 1.0], [0.9, 0.1, 0.5]) == 2  # ties: the median brightness

    def test_even_count_takes_the_upper_middle_view(self):
        assert choose_reference([1.2, 0.15, 0.6, 0.3], [0.0] * 4) == 2  # 0.6 s, not 0.3 s
        assert choose_reference([0.5, 0.5, 0.5, 2.0], [0.0] * 4) == 2  # over views: 0.5 s, not the distinct 0.5/2


def auto_exposed(scene, exposures, known: bool):
    """The voxel capture re-photographed at a different exposure per training view (gamma 2.2)."""
    from dataclasses import replace as replace_view

    from mono_hdr_plugin.data.dataset import SceneData

    train = [
        replace_view(view, image=(view.hdr * exposure).clamp(0, 1) ** (1 / 2.2), exposure=exposure if known else 1.0)
        for view, exposure in zip(scene.train, exposures)
    ]
    gamma = np.stack([np.linspace(0, 1, 256) ** 2.2] * 3, -1)
    metadata = {"camera_response": gamma.tolist(), "unknown_exposures": [] if known else [view.name for view in train]}
    return SceneData(
        name="auto",
        train=train,
        test=scene.test,
        bounds_min=scene.bounds_min,
        bounds_max=scene.bounds_max,
        metadata=metadata,
    )


class TestTraining:
    """The trainer gives each view its exposure: the view index reaches the pipeline, corrections learn,
    and the learned values are written and saved."""

    exposures = [0.5, 0.9, 0.3, 0.6]

    def run(
        self,
        voxel_scene,
        voxel_backbone_config,
        tmp_path,
        known: bool,
        method: str = "mono",
        steps: int = 6,
        learn: bool | None = None,
    ):
        from mono_hdr_plugin.training.trainer import Trainer

        config = quiet_config(voxel_backbone_config, tmp_path / "run", method, max_steps=steps, max_eval_views=2)
        config.exposure.learn_exposure = learn
        return Trainer(config, "voxel-grid", auto_exposed(voxel_scene, self.exposures, known))

    def test_known_auto_exposure_is_fixed(self, voxel_scene, voxel_backbone_config, tmp_path):
        trainer = self.run(voxel_scene, voxel_backbone_config, tmp_path, known=True)
        exposures = trainer.pipeline.exposures
        assert not exposures.learned and float(exposures.reference_exposure) == pytest.approx(0.6)  # upper median of 4
        # the viewer's EV 0 is the exposure training is anchored at (one rule, core.exposure.choose_reference)
        scene = auto_exposed(voxel_scene, self.exposures, known=True)
        assert calibrate(trainer.pipeline, scene).reference_exposure == pytest.approx(0.6)
        np.testing.assert_allclose(exposures.relative_exposures().numpy(), np.array(self.exposures) / 0.6, rtol=1e-6)

    @pytest.mark.parametrize("method", ["mono", "hdr-gs"])
    def test_unknown_exposures_learn(self, voxel_scene, voxel_backbone_config, tmp_path, method):
        trainer = self.run(voxel_scene, voxel_backbone_config, tmp_path, known=False, method=method)
        exposures = trainer.pipeline.exposures
        assert exposures.learned
        before = exposures.relative_exposures().clone()
        metrics = trainer.train()
        moved = exposures.relative_exposures() != before
        assert moved.sum() >= 2 and not moved[int(exposures.reference)]  # the reference stays fixed
        report = json.loads((tmp_path / "run" / "learned_exposures.json").read_text())
        assert report["learned"] and report["reference_exposure"] is None
        assert report["views"][trainer.scene.train[1].name]["relative"] == pytest.approx(
            float(exposures.relative_exposures()[1])
        )
        assert metrics["ldr_exposure_fitted"] == 0  # the test views kept their known exposure

    def test_right_exposures_stay_right_while_learning(self, voxel_scene, voxel_backbone_config, tmp_path):
        # Known exposures learned from their true values: Adam moves each by about its learning rate
        # a step whatever the gradient, so the default rate must keep this walk small (at 0.01 these
        # 60 steps take one 13 % away).
        trainer = self.run(voxel_scene, voxel_backbone_config, tmp_path, known=True, steps=60, learn=True)
        assert trainer.pipeline.exposures.learned
        trainer.train()
        relative = trainer.pipeline.exposures.relative_exposures().numpy()
        np.testing.assert_allclose(relative, np.array(self.exposures) / 0.6, rtol=0.03)

    def test_checkpoint_keeps_the_exposures(self, voxel_scene, voxel_backbone_config, tmp_path):
        from mono_hdr_plugin.training.trained import load_trained_model

        trainer = self.run(voxel_scene, voxel_backbone_config, tmp_path, known=False)
        trainer.train()
        loaded = load_trained_model(trainer.checkpoint_path(), scene=trainer.scene).pipeline
        torch.testing.assert_close(
            loaded.exposures.relative_exposures(), trainer.pipeline.exposures.relative_exposures()
        )
        camera, exposure = trainer.scene.test[0].camera, trainer.scene.test[0].exposure
        with trainer.pipeline.evaluating():
            expected = trainer.pipeline.render(camera, exposure)
        torch.testing.assert_close(loaded.render(camera, exposure).ldr, expected.ldr)
