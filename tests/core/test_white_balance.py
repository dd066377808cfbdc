"""White balance per view (core.white_balance) and the held-out appearance protocol (training.appearance):
gains applied in linear light, their gauge, learning them, fitting a held-out view's, and the runs."""

import json
import math
from dataclasses import replace

import colour
import numpy as np
import pytest
import torch
from helpers import quiet_config

from mono_hdr_plugin.core.exposure import (
    ExposureConfig,
    ViewExposures,
    brighten,
    build_view_exposures,
    fit_log_scales,
    srgb_response,
)
from mono_hdr_plugin.core.white_balance import ViewWhiteBalance, split_log_scales
from mono_hdr_plugin.training.appearance import APPEARANCE_PROTOCOL, appearance_fitted_scores
from mono_hdr_plugin.training.hdr_prior import hdr_basis
from mono_hdr_plugin.training.pipeline import Frame

SRGB = torch.from_numpy(srgb_response()).float()


def random_image(seed: int, shape=(8, 8, 3)) -> torch.Tensor:
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) * 0.6 + 0.1


def srgb_linear(code: torch.Tensor) -> np.ndarray:
    """sRGB code values -> linear light by colour-science, a reference independent of core.exposure."""
    return colour.cctf_decoding(code.double().numpy(), function="sRGB")


def with_corrections(module: ViewWhiteBalance, values) -> ViewWhiteBalance:
    with torch.no_grad():
        for correction, value in zip(module.correction, values):
            correction.copy_(torch.tensor(value))
    return module


class TestGainApplication:
    def test_gains_scale_each_channel_in_linear_light(self):
        ldr = random_image(0) * 0.5
        log_scale = torch.log(torch.tensor([1.5, 0.8, 1.2]))
        photo = brighten(ldr, log_scale, SRGB)
        np.testing.assert_allclose(srgb_linear(photo), srgb_linear(ldr) * [1.5, 0.8, 1.2], rtol=3e-3, atol=1e-5)

    def test_gradcheck(self):
        response = SRGB.double()
        code = torch.tensor([[0.2013, 0.3021, 0.4007], [0.3109, 0.2417, 0.1031]], dtype=torch.float64)
        log_scale = torch.tensor([0.11, -0.07, 0.05], dtype=torch.float64, requires_grad=True)
        assert torch.autograd.gradcheck(lambda s: brighten(code, s, response), (log_scale,))
        ldr = code.clone().requires_grad_(True)
        assert torch.autograd.gradcheck(lambda x: brighten(x, log_scale.detach(), response), (ldr,))


class TestGauge:
    raw = np.array([[0.3, -0.1, 0.2], [0.0, 0.4, -0.3], [-0.2, 0.1, 0.5]])

    def test_log_gains_have_zero_mean_over_channels_and_views(self):
        module = with_corrections(ViewWhiteBalance(3, 0.1, 0.0), self.raw)
        centred = self.raw - self.raw.mean(0)
        expected = centred - centred.mean(1, keepdims=True)
        np.testing.assert_allclose(np.log(module.gains().numpy()), expected, atol=1e-6)

    def test_a_held_out_view_gets_the_mean_balance(self):
        module = with_corrections(ViewWhiteBalance(3, 0.1, 0.0), self.raw)
        assert torch.equal(module.log_gains(None), torch.zeros(3))

    def test_gradient_is_projected_on_the_gauge(self):
        module = with_corrections(ViewWhiteBalance(3, 0.1, 0.0), self.raw)
        weights = np.array([1.0, 2.0, -1.0])
        (module.log_gains(1) * torch.tensor(weights).float()).sum().backward()
        # d/dc_k of (c_1 - mean_views c - its channel mean) . w = ([k == 1] - 1/3) (w - mean(w))
        projected = weights - weights.mean()
        for k, correction in enumerate(module.correction):
            np.testing.assert_allclose(correction.grad.numpy(), ((k == 1) - 1 / 3) * projected, atol=1e-6)

    def test_pull_is_the_mean_squared_log_gain(self):
        module = with_corrections(ViewWhiteBalance(3, 0.1, 0.5), self.raw)
        centred = self.raw - self.raw.mean(0)
        expected = 0.5 * ((centred - centred.mean(1, keepdims=True)) ** 2).sum(1).mean()
        assert module.regularisation()["white_balance_pull"].item() == pytest.approx(expected, rel=1e-5)
        assert ViewWhiteBalance(3, 0.1, 0.0).regularisation() == {}

    def test_split_gives_one_exposure_and_colour_gains(self):
        log_exposure, gains = split_log_scales(torch.log(torch.tensor([2.0, 1.0, 4.0])))
        assert log_exposure.item() == pytest.approx(math.log(2.0))  # the geometric mean of 2, 1, 4
        np.testing.assert_allclose(gains.numpy(), [1.0, 0.5, 2.0], rtol=1e-6)


def balanced_exposures(views: int, pull: float = 0.0) -> ViewExposures:
    return ViewExposures(
        torch.zeros(views), 0, 1.0, srgb_response(), learn=False, white_balance=ViewWhiteBalance(views, 0.05, pull)
    )


class TestLearning:
    true_gains = np.exp(np.array([[0.0, 0.0, 0.0], [0.3, -0.1, -0.2], [-0.25, 0.15, 0.1], [0.1, 0.2, -0.3]]))

    def learn(self, true_gains: np.ndarray):
        """Photos of one canonical image under known gains; image and gains learned from the photos."""
        canonical = random_image(2) * 0.5
        module = balanced_exposures(len(true_gains))
        photos = [brighten(canonical, torch.log(torch.tensor(g)).float(), SRGB) for g in true_gains]
        logits = torch.zeros_like(canonical, requires_grad=True)
        optimiser = torch.optim.Adam(
            [{"params": [logits], "lr": 0.1}, {"params": list(module.white_balance.correction), "lr": 0.05}]
        )
        decay = torch.optim.lr_scheduler.ExponentialLR(optimiser, gamma=0.995)
        for step in range(800):
            view = step % len(photos)
            loss = torch.abs(module.brighten(torch.sigmoid(logits), module.log_scale(view)) - photos[view]).mean()
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            decay.step()
        return module.white_balance.gains().numpy(), srgb_linear(torch.sigmoid(logits).detach()), srgb_linear(canonical)

    def test_recovers_the_gains_and_keeps_the_colour(self):
        centred = np.log(self.true_gains) - np.log(self.true_gains).mean(0)  # zero mean over views: no cast
        gains, learned, canonical = self.learn(np.exp(centred))
        np.testing.assert_allclose(gains, np.exp(centred), rtol=0.01)
        np.testing.assert_allclose(learned, canonical, rtol=0.02, atol=2e-3)

    def test_a_cast_on_every_photo_goes_to_the_scene(self):
        # Every photo 20 % redder than the gains say: the gauge (zero mean over views) gives the gains
        # back without the cast, and the canonical image carries it.
        gains, learned, canonical = self.learn(self.true_gains * [1.2, 1.0, 1.0])
        log_true = np.log(self.true_gains)
        np.testing.assert_allclose(np.log(gains), log_true - log_true.mean(0), atol=0.01)
        cast = np.exp(log_true.mean(0)) * [1.2, 1.0, 1.0]
        np.testing.assert_allclose(learned, canonical * cast, rtol=0.02, atol=2e-3)


class TestHeldOutFit:
    def photo(self, gains, exposure: float = 1.3, seed: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
        render = random_image(seed, (24, 32, 3)) * 0.5
        return render, brighten(render, torch.log(exposure * torch.tensor(gains)), SRGB)

    def test_recovers_the_exposure_and_gains_of_a_photo(self):
        render, photo = self.photo([1.25, 1.0, 0.8])
        log_exposure, gains = split_log_scales(fit_log_scales(render, photo, SRGB))
        # gains in the gauge: geometric mean 1 (1.25 * 0.8 = 1)
        np.testing.assert_allclose(gains.numpy(), [1.25, 1.0, 0.8], rtol=2e-3)
        assert math.exp(log_exposure.item()) == pytest.approx(1.3, rel=2e-3)

    def test_right_half_of_a_rendered_photo_scores_near_perfect(self):
        render, photo = self.photo([1.1, 0.95, 1 / (1.1 * 0.95)])
        scores = appearance_fitted_scores(Frame(render, render, None, None, 1.0), photo, SRGB)
        assert scores["ldr_psnr_appearance_fitted"] > 55 and scores["ldr_ssim_appearance_fitted"] > 0.9999
        np.testing.assert_allclose(scores["appearance_fitted_gains"], [1.1, 0.95, 1 / (1.1 * 0.95)], rtol=2e-3)

    def test_the_fit_sees_only_the_left_half(self):
        # The right half of the photo under other gains: the fit keeps the left half's, and the score
        # on the right is the error the left-half gains make there (an independent PSNR by numpy).
        render, left_photo = self.photo([1.2, 1.0, 1 / 1.2])
        _, right_photo = self.photo([0.9, 1.0, 1 / 0.9])
        photo = torch.cat([left_photo[:, :16], right_photo[:, 16:]], 1)
        scores = appearance_fitted_scores(Frame(render, render, None, None, 1.0), photo, SRGB)
        np.testing.assert_allclose(scores["appearance_fitted_gains"], [1.2, 1.0, 1 / 1.2], rtol=2e-3)
        error = np.mean((left_photo[:, 16:].double().numpy() - right_photo[:, 16:].double().numpy()) ** 2)
        assert scores["ldr_psnr_appearance_fitted"] == pytest.approx(-10 * math.log10(error), abs=0.05)


class FakeView:
    def __init__(self, exposure, name):
        self.exposure, self.name, self.image = exposure, name, torch.full((2, 2, 3), 0.5)


class FakeScene:
    def __init__(self, exposures, unknown=(), auto_white_balance=()):
        self.train = [FakeView(e, f"{i:03d}_0.png") for i, e in enumerate(exposures)]
        self.metadata = {"unknown_exposures": list(unknown), "auto_white_balance": list(auto_white_balance)}
        self.points = None


class TestBuild:
    def test_studio_default_learns_no_white_balance(self):
        assert build_view_exposures(ExposureConfig(), FakeScene([0.5, 0.5])) is None
        assert build_view_exposures(ExposureConfig(), FakeScene([0.5, 1.0])).white_balance is None

    def test_auto_learns_it_with_unknown_exposures(self):
        module = build_view_exposures(ExposureConfig(), FakeScene([1.0, 1.0], unknown=["000_0.png", "001_0.png"]))
        assert module.white_balance is not None and [g["name"] for g in module.parameter_groups()] == [
            "exposures",
            "white_balance",
        ]

    def test_auto_learns_it_where_the_camera_balanced_white(self):
        module = build_view_exposures(ExposureConfig(), FakeScene([0.5, 1.0], auto_white_balance=["000_0.png"]))
        assert module.white_balance is not None and not module.learned  # EXIF times: exposures stay

    def test_a_run_saved_before_white_balance_learned_none(self):
        from mono_hdr_plugin.core.configs import config_from_dict

        assert config_from_dict(ExposureConfig, {"learn_exposure": None}).learn_white_balance == "off"

    def test_flags(self):
        config = ExposureConfig(learn_white_balance="on", white_balance_lr=0.02, white_balance_pull=0.3)
        module = build_view_exposures(config, FakeScene([0.5, 0.5]))
        assert module.parameter_groups() == [
            {"name": "white_balance", "params": list(module.white_balance.correction), "lr": 0.02}
        ]
        assert module.white_balance.pull_weight == 0.3
        scene = FakeScene([1.0, 1.0], unknown=["000_0.png"])
        assert build_view_exposures(ExposureConfig(learn_white_balance="off"), scene).white_balance is None


def white_balanced(scene, gains: np.ndarray):
    """The voxel capture with each training photo under its own white balance (gamma 2.2, linear gains)."""
    from mono_hdr_plugin.data.dataset import SceneData

    exposure = scene.train[0].exposure
    train = [
        replace(view, image=(view.hdr * exposure * torch.tensor(g).float()).clamp(0, 1) ** (1 / 2.2))
        for view, g in zip(scene.train, gains)
    ]
    gamma = np.stack([np.linspace(0, 1, 256) ** 2.2] * 3, -1)
    metadata = {"camera_response": gamma.tolist(), "unknown_exposures": []}
    return SceneData("balanced", train, scene.test, scene.bounds_min, scene.bounds_max, metadata=metadata)


class TestTraining:
    """Runs of the voxel backbone: the studio default untouched, gains learned, written, saved and resumed."""

    gains = np.exp(np.array([[0.2, 0.0, -0.2], [-0.2, 0.1, 0.1], [0.1, -0.15, 0.05], [-0.1, 0.05, 0.05]]))

    def trainer(self, voxel_scene, voxel_backbone_config, out, method="mono", steps=6, **exposure):
        from mono_hdr_plugin.training.trainer import Trainer

        config = quiet_config(voxel_backbone_config, out, method, max_steps=steps, max_eval_views=2)
        config.exposure = ExposureConfig(**exposure)
        return Trainer(config, "voxel-grid", white_balanced(voxel_scene, self.gains))

    def test_studio_default_changes_nothing(self, voxel_scene, voxel_backbone_config, tmp_path):
        from mono_hdr_plugin.training.trainer import Trainer

        trainer = Trainer(quiet_config(voxel_backbone_config, tmp_path, max_steps=2), "voxel-grid", voxel_scene)
        assert trainer.pipeline.exposures is None
        metrics = trainer.train()
        assert "appearance_protocol" not in metrics and "ldr_psnr_appearance_fitted" not in metrics

    def test_gains_at_their_start_render_what_no_gains_render(self, voxel_scene, voxel_backbone_config, tmp_path):
        plain = self.trainer(voxel_scene, voxel_backbone_config, tmp_path / "a").pipeline
        balanced = self.trainer(voxel_scene, voxel_backbone_config, tmp_path / "b", learn_white_balance="on").pipeline
        assert plain.exposures is None and balanced.exposures.white_balance is not None
        balanced.backbone.load_state_dict(plain.backbone.state_dict())
        balanced.method.load_state_dict(plain.method.state_dict())
        view = voxel_scene.test[0]
        with plain.evaluating(), balanced.evaluating():
            torch.testing.assert_close(
                balanced.render(view.camera, view.exposure).ldr,
                plain.render(view.camera, view.exposure).ldr,
                atol=2e-5,
                rtol=0,
            )

    def test_gains_learn_the_truth(self, voxel_scene, voxel_backbone_config, tmp_path):
        # HDR-GS (exposure through its CRF, gains with it); Mono-HDR does not fit this toy backbone
        # (13.7 dB with or without gains), so its run is checked for wiring below.
        trainer = self.trainer(
            voxel_scene,
            voxel_backbone_config,
            tmp_path,
            "hdr-gs",
            1000,
            learn_white_balance="on",
            white_balance_lr=0.01,
        )
        trainer.train()
        learned = np.log(trainer.pipeline.exposures.white_balance.gains().numpy())
        truth = np.log(self.gains) - np.log(self.gains).mean(0)
        truth -= truth.mean(1, keepdims=True)
        np.testing.assert_allclose(learned, truth, atol=0.1)
        assert np.corrcoef(learned.ravel(), truth.ravel())[0, 1] > 0.9

    def test_strong_pull_holds_the_gains_at_the_mean(self, voxel_scene, voxel_backbone_config, tmp_path):
        trainer = self.trainer(
            voxel_scene,
            voxel_backbone_config,
            tmp_path,
            "hdr-gs",
            150,
            learn_white_balance="on",
            white_balance_pull=1.0,
        )
        trainer.train()
        assert np.abs(np.log(trainer.pipeline.exposures.white_balance.gains().numpy())).max() < 0.02

    def test_run_writes_and_scores_the_appearance(self, voxel_scene, voxel_backbone_config, tmp_path):
        trainer = self.trainer(voxel_scene, voxel_backbone_config, tmp_path, learn_white_balance="on")
        metrics = trainer.train()
        gains = trainer.pipeline.exposures.white_balance.gains().numpy()
        report = json.loads((tmp_path / "learned_exposures.json").read_text())
        np.testing.assert_allclose(report["white_balance"]["views"][trainer.scene.train[1].name], gains[1], rtol=1e-6)
        assert metrics["appearance_protocol"] == APPEARANCE_PROTOCOL
        basis = hdr_basis(trainer.scene, [False] * 4, trainer.pipeline.exposures)  # as without HDR views
        assert basis.endswith("; white balance per view, learned (the HDR keeps the photos' mean balance)")
        assert metrics["ldr_psnr_appearance_fitted"] == pytest.approx(
            np.mean([row["ldr_psnr_appearance_fitted"] for row in metrics["views"]])
        )
        assert metrics["ldr_ssim_appearance_fitted"] is None  # 8 px half images: narrower than SSIM's window

    def test_checkpoint_and_resume_keep_the_gains(self, voxel_scene, voxel_backbone_config, tmp_path):
        from mono_hdr_plugin.training.trained import load_trained_model

        trainer = self.trainer(voxel_scene, voxel_backbone_config, tmp_path, steps=8, learn_white_balance="on")
        trainer.train()
        gains = trainer.pipeline.exposures.white_balance.gains()
        assert not torch.allclose(gains, torch.ones_like(gains))
        loaded = load_trained_model(trainer.checkpoint_path(), scene=trainer.scene).pipeline
        torch.testing.assert_close(loaded.exposures.white_balance.gains(), gains)
        resumed = self.trainer(voxel_scene, voxel_backbone_config, tmp_path, steps=10, learn_white_balance="on")
        resumed.config.resume = True
        from mono_hdr_plugin.training.checkpoints import load_checkpoint

        resumed.restore(load_checkpoint(trainer.checkpoint_path()))
        torch.testing.assert_close(resumed.pipeline.exposures.white_balance.gains(), gains)
        names = [group["name"] for group in resumed.optimizer.param_groups]
        group = resumed.optimizer.param_groups[names.index("white_balance")]
        assert all(resumed.optimizer.state[p]["step"] == 8 for p in group["params"])  # Adam's moments came back
