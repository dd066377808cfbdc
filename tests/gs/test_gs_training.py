"""Two real training steps of every method with the 3DGS backbone, resume across densification,
and a short run on the default studio scene whose HDR PSNR rises."""

import math

import pytest
import torch
from helpers import quiet_config

from backbones.gs import DefaultStrategy, GaussianBackbone, GaussianConfig
from mono_hdr_plugin.methods.base import method_names
from mono_hdr_plugin.training.checkpoints import load_checkpoint
from mono_hdr_plugin.training.trainer import Trainer


def gs_trainer(tmp_path, scene, method: str = "mono", max_steps: int = 2, **backbone_overrides) -> Trainer:
    backbone = GaussianConfig(random_init_points=500, **backbone_overrides)
    config = quiet_config(backbone, tmp_path / "run", method, max_steps=max_steps)
    return Trainer(config, "gs", scene)


class TestTwoStepsOfEveryMethod:
    @pytest.mark.parametrize("method", method_names())
    def test_two_steps(self, tmp_path, voxel_scene, method):
        trainer = gs_trainer(tmp_path, voxel_scene, method)
        before = [p.detach().clone() for p in trainer.backbone.parameters()]
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] for r in records)
        assert any(not torch.equal(a, b) for a, b in zip(before, trainer.backbone.parameters()))

    @pytest.mark.parametrize("method", ["mono", "hdr-gs"])
    def test_two_steps_with_an_environment(self, tmp_path, voxel_scene, method):
        """The methods take the background rows like any Gaussian's and train the sky with them."""
        trainer = gs_trainer(tmp_path, voxel_scene, method, background="environment")
        sky = [p.detach().clone() for p in trainer.backbone.environment.parameters()]
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] for r in records)
        assert any(not torch.equal(a, b) for a, b in zip(sky, trainer.backbone.environment.parameters()))

    def test_converter_learning_rate_is_configurable(self, tmp_path, voxel_scene):
        trainer = gs_trainer(tmp_path, voxel_scene)
        trainer.config.hdr.converter_lr = 1e-2
        trainer = Trainer(trainer.config, "gs", voxel_scene)
        method_group = next(g for g in trainer.optimizer.param_groups if g["name"] == "method")
        assert method_group["lr"] == 1e-2


class TestResumeAcrossDensification:
    def test_checkpoint_after_densify_restores_same_next_loss(self, tmp_path, voxel_scene):
        # max_steps = 30k keeps the schedule unscaled: refine at steps 2 and 4
        strategy = DefaultStrategy(
            refine_start=2, refine_every=2, min_refine_every=1, grad_threshold=0.0, reset_opacity_every=10**6
        )
        trainer = gs_trainer(tmp_path, voxel_scene, max_steps=30_000, strategy=strategy)
        for _ in range(5):
            trainer.train_step()
        count = trainer.backbone.means.shape[0]
        assert count != 500  # densification changed the number of Gaussians
        trainer.save()
        expected = trainer.train_step()["loss"]
        resumed = gs_trainer(tmp_path, voxel_scene, max_steps=30_000, strategy=strategy)
        resumed.restore(load_checkpoint(trainer.checkpoint_path()))
        assert resumed.backbone.means.shape[0] == count
        assert resumed.train_step()["loss"] == pytest.approx(expected, rel=1e-5)


def hot_chromaticity(hdr: torch.Tensor, hot: torch.Tensor) -> torch.Tensor:
    """Mean r, g, b chromaticity (each channel over their sum) of the pixels `hot` [H, W] of `hdr` [H, W, 3]."""
    colours = hdr[hot]
    return (colours / colours.sum(-1, keepdim=True).clamp_min(1e-12)).mean(0)


def studio_trainer(tmp_path, preset: str, steps: int) -> Trainer:
    from mono_hdr_plugin.data.config import DataConfig
    from mono_hdr_plugin.data.loading import load_scene

    scene = load_scene(DataConfig(scene="demo"))
    backbone = GaussianBackbone.presets()[preset]
    config = quiet_config(backbone, tmp_path / preset, preset=preset, max_steps=steps, max_eval_views=4)
    return Trainer(config, "gs", scene)


@pytest.mark.slow
class TestShortStudioRun:
    def test_cpu_recipe_learns_hdr_in_500_steps(self, tmp_path):
        """500 steps on the 128 px demo: the cpu preset passes 30 dB HDR PSNR (34.7 dB when this was
        written; 39.7 dB after `make demo`'s 1000 steps). Before the cpu preset, 500 steps of the
        official recipe gave 19.8 dB on the easier 64 px demo (benchmarks/results/earlier-8232d53)."""
        cpu = studio_trainer(tmp_path, "cpu", 500)
        before = cpu.evaluate()
        after = cpu.train()
        assert after["hdr_psnr"] > 30.0
        assert after["ldr_psnr"] > before["ldr_psnr"] + 10.0

    def test_hottest_pixels_keep_their_hue(self, tmp_path):
        """The demo's bulb is white (warm) in the ground truth: its HDR render must keep that hue.
        Bound: the mean over four test views of the summed |chromaticity| error under 0.35 (a clipped-white
        bulb rendered cyan was 0.53). The error moves from run to run with float summation order (the
        backward kernel hands tiles to threads dynamically, each summing its own gradients): 0.09-0.15 per
        view in four runs with 2 threads, 0.17-0.19 with 1, one view at 0.28 on a CI machine, so one view's
        error is no verdict."""
        trainer = studio_trainer(tmp_path, "cpu", 800)
        trainer.train()
        trainer.backbone.eval()
        trainer.method.eval()
        errors = []
        with torch.no_grad():
            for view in trainer.scene.test[:4]:
                hdr = trainer.method(trainer.backbone.render_ldr_features(view.camera), view.exposure).hdr
                luminance = view.hdr @ torch.tensor([0.2126, 0.7152, 0.0722])
                hot = luminance >= torch.quantile(luminance.flatten(), 0.995)
                errors.append(float((hot_chromaticity(hdr, hot) - hot_chromaticity(view.hdr, hot)).abs().sum()))
        assert sum(errors) / len(errors) < 0.35, f"hottest pixels shifted in chromaticity by {errors}"


class SlowingClock:
    """perf_counter for the trainer (read twice a step): each step takes `first` seconds plus
    `growth` more than the one before, as steps slow down while Gaussians are added."""

    def __init__(self, first: float, growth: float):
        self.now, self.calls, self.first, self.growth = 0.0, 0, first, growth

    def perf_counter(self) -> float:
        self.calls += 1
        if self.calls % 2 == 0:  # the end of a step
            self.now += self.first + self.growth * (self.calls // 2 - 1)
        return self.now


class TestTimeBudget:
    """--max-seconds with the 3DGS backbone: stops on time, re-scales its schedules as the step
    time changes, keeps every learned state, and resumes where it stopped."""

    @pytest.fixture
    def slowing_clock(self, monkeypatch):
        import mono_hdr_plugin.training.trainer as train_module

        clock = SlowingClock(first=0.1, growth=0.004)
        monkeypatch.setattr(train_module.time, "perf_counter", clock.perf_counter)
        return clock

    def budget_trainer(self, tmp_path, scene, seconds: float) -> Trainer:
        backbone = GaussianBackbone.presets()["cpu"]
        config = quiet_config(
            backbone,
            tmp_path / "run",
            max_steps=100_000,
            max_seconds=seconds,
            max_eval_views=1,
        )
        return Trainer(config, "gs", scene)

    def test_stops_on_time_and_rescales_every_estimate(self, tmp_path, voxel_scene, slowing_clock, monkeypatch):
        trainer = self.budget_trainer(tmp_path, voxel_scene, seconds=12.0)
        lengths, degrees = [], []
        original = trainer.backbone.set_run_length
        monkeypatch.setattr(trainer.backbone, "set_run_length", lambda n: (lengths.append(n), original(n)))
        while not trainer.finished:
            trainer.train_step()
            degrees.append(trainer.backbone.active_sh_degree)
            assert trainer.backbone.num_gaussians <= trainer.backbone.budget
        assert trainer.train_seconds >= 12.0 > trainer.train_seconds - (0.1 + 0.004 * (trainer.step - 1))
        assert len(lengths) >= 3, "slowing steps must move the estimate more than once"
        assert lengths == sorted(lengths, reverse=True), "each estimate is shorter than the last"
        assert trainer.backbone.max_steps == trainer.run_length == lengths[-1]
        assert abs(trainer.run_length - trainer.step) <= 0.1 * trainer.step, "the last estimate is close to the end"
        assert degrees == sorted(degrees) and degrees[-1] == 3, "the SH ramp never goes back and completes"

    def test_resume_keeps_budget_schedule_and_strategy_state(self, tmp_path, voxel_scene, slowing_clock):
        trainer = self.budget_trainer(tmp_path, voxel_scene, seconds=12.0)
        for _ in range(40):
            trainer.train_step()
        trainer.save()
        saved = {
            "run_length": trainer.run_length,
            "degree": trainer.backbone.active_sh_degree,
            "count": trainer.backbone.num_gaussians,
            "seconds": trainer.train_seconds,
        }
        resumed = self.budget_trainer(tmp_path, voxel_scene, seconds=12.0)
        resumed.restore(load_checkpoint(trainer.checkpoint_path()))
        assert resumed.backbone.max_steps == resumed.run_length == saved["run_length"]
        assert resumed.backbone.active_sh_degree == saved["degree"]
        assert resumed.backbone.num_gaussians == saved["count"]
        assert resumed.train_seconds == pytest.approx(saved["seconds"])
        while not resumed.finished:
            resumed.train_step()
        assert resumed.train_seconds >= 12.0 and resumed.step > 40


class TestScenePointsStayPut:
    def test_training_does_not_move_the_scene_points(self, tmp_path, voxel_scene):
        """The means start from the scene's points: they must be a copy, or a second run in the same
        process (benchmarks, tests) starts from the first run's trained means."""
        from dataclasses import replace

        points = torch.rand(300, 3) * 2 - 1
        scene = replace(voxel_scene, points=points, point_colors=torch.rand(300, 3))
        before = points.clone()
        trainer = gs_trainer(tmp_path, scene, max_steps=3)
        for _ in range(3):
            trainer.train_step()
        assert not torch.equal(trainer.backbone.means.detach()[:300], before)  # the means did move
        assert torch.equal(scene.points, before)
