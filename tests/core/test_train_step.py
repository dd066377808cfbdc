"""One training step in detail: seeds, which views get HDR, pixel batches, the first Adam step,
the non-finite gradient guard, what the step records and what it tells the backbone."""

import dataclasses
import math

import numpy as np
import pytest
import register_backbone  # examples/, put on sys.path by conftest
import torch
from helpers import quiet_config
from known_render import KnownRenderConfig, expected_render, known_scene
from skimage.metrics import peak_signal_noise_ratio

from mono_hdr_plugin.training.config import hdr_supervised_views, train_config_for
from mono_hdr_plugin.training.trainer import Trainer


def voxel_trainer(tmp_path, scene, **options) -> Trainer:
    backbone = register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24)
    config = quiet_config(backbone, tmp_path / "run", max_steps=10, **options)
    return Trainer(config, "voxel-grid", scene)


class TestHdrViewSelection:
    @pytest.mark.parametrize(
        "views,ratio,chosen",
        [
            (9, "2:1", [0, 1, 3, 5, 7]),  # ceil(9 / 2) = 5 views, spread evenly
            (9, "3:1", [0, 3, 6]),
            (10, "5:1", [0, 5]),
            (3, "5:1", [0]),  # at least one view keeps its HDR
            (4, "1:1", [0, 1, 2, 3]),
            (4, "1:2", [0, 1, 2, 3]),  # more HDR than LDR views: all of them
            (4, "1:0", []),
        ],
    )
    def test_which_views(self, views, ratio, chosen):
        selected = hdr_supervised_views(views, ratio)
        assert len(selected) == views
        assert [i for i, keep in enumerate(selected) if keep] == chosen


class TestLearnedExposures:
    def test_a_step_leaves_the_exposures_of_views_it_does_not_train_alone(self, tmp_path, voxel_scene):
        # One tensor per view, and gradients set to None between steps: Adam skips the views a step
        # does not see (zeroed gradients would let their momentum carry them on).
        unknown = [view.name for view in voxel_scene.train]
        scene = dataclasses.replace(voxel_scene, metadata={**voxel_scene.metadata, "unknown_exposures": unknown})
        trainer = voxel_trainer(tmp_path, scene)
        exposures = trainer.pipeline.exposures
        first, second = [v for v in range(len(scene.train)) if v != int(exposures.reference)][:2]
        trainer.view_order = [second, first]  # popped from the end: `first` trains first
        start = exposures.relative_exposures()
        trainer.train_step()
        after_one = exposures.relative_exposures()
        trainer.train_step()
        after_two = exposures.relative_exposures()
        assert after_one[first] != start[first] and after_one[second] == start[second]
        assert after_two[first] == after_one[first] and after_two[second] != after_one[second]


class TestInitialisation:
    def test_the_seed_decides_the_initial_model(self, tmp_path, voxel_scene):
        first, again = (voxel_trainer(tmp_path, voxel_scene, seed=5) for _ in range(2))
        other = voxel_trainer(tmp_path, voxel_scene, seed=6)
        for (name, a), b in zip(first.pipeline.named_parameters(), again.pipeline.parameters()):
            assert torch.equal(a, b), name
        assert any(not torch.equal(a, c) for a, c in zip(first.method.parameters(), other.method.parameters()))

    def test_first_adam_step_moves_each_parameter_by_its_learning_rate(self, tmp_path, voxel_scene):
        """Adam's first step is lr * g / (|g| + eps): with the tiny eps of 3DGS that is lr per coordinate."""
        trainer = voxel_trainer(tmp_path, voxel_scene)
        rates = {id(p): group["lr"] for group in trainer.optimizer.param_groups for p in group["params"]}
        before = {name: p.detach().clone() for name, p in trainer.pipeline.named_parameters()}
        trainer.train_step()
        moved_somewhere = set()
        for name, parameter in trainer.pipeline.named_parameters():
            step = (parameter.detach() - before[name]).abs()
            moved = step[step > 0]
            if moved.numel():
                moved_somewhere.add(name.split(".")[1])
                ratio = moved / rates[id(parameter)]
                assert ratio.max() < 1 + 1e-4, name
                assert (ratio > 1 - 1e-3).float().mean() > 0.95, name  # all but coordinates with |g| ~ eps
        assert moved_somewhere == {"density", "color_logits", "l2h", "h2l"}
        assert {g["name"]: g["lr"] for g in trainer.optimizer.param_groups} == {"grid": 0.1, "method": 5e-4}


class TestPixelBatches:
    def test_targets_are_the_pixels_rendered(self, tmp_path, voxel_scene, monkeypatch):
        trainer = voxel_trainer(tmp_path, voxel_scene)
        monkeypatch.setattr(trainer.backbone, "pixel_batch", 4000)
        view = voxel_scene.train[1]
        trainer.hdr_views[1] = True
        camera, targets = trainer._batch(view, 1)
        pixels = camera.pixels
        assert pixels.shape == (4000, 2) and targets.ldr.shape == targets.hdr.shape == (4000, 3)
        columns, rows = (pixels - 0.5).long().unbind(-1)
        torch.testing.assert_close(pixels, torch.stack([columns, rows], -1).float() + 0.5)  # pixel centres
        torch.testing.assert_close(targets.ldr, view.image[rows, columns])
        torch.testing.assert_close(targets.hdr, view.hdr[rows, columns])
        assert targets.exposure == view.exposure
        # 4000 draws from 256 pixels reach every one of them (the chance to miss one is 1e-4)
        assert torch.unique(rows * 16 + columns).numel() == 256
        trainer.hdr_views[1] = False
        _, without_hdr = trainer._batch(view, 1)
        assert without_hdr.hdr is None

    def test_every_batch_holds_the_brightest_pixel(self, tmp_path, voxel_scene, monkeypatch):
        """L_hdr divides a batch by its own maximum: a batch that missed a few-pixel source would be
        normalised by something 1000x dimmer. The source here is one pixel, 64x the rest."""
        trainer = voxel_trainer(tmp_path, voxel_scene)
        monkeypatch.setattr(trainer.backbone, "pixel_batch", 8)  # 8 draws of 256 pixels miss one pixel 97 % of the time
        view = voxel_scene.train[0]
        hdr = view.hdr.clone()
        hdr[11, 5] = 64.0 * hdr.max()
        view = dataclasses.replace(view, hdr=hdr)
        trainer.hdr_views[0] = True
        for _ in range(20):
            camera, targets = trainer._batch(view, 0)
            assert targets.hdr.max() == hdr.max()
            assert (camera.pixels == torch.tensor([5.5, 11.5])).all(-1).any()


class TestNonFiniteGradients:
    def test_a_step_with_a_nan_gradient_is_skipped_and_the_next_one_trains(self, tmp_path, voxel_scene):
        trainer = voxel_trainer(tmp_path, voxel_scene)
        density = trainer.backbone.density
        handle = density.register_hook(lambda grad: grad * math.nan)
        before = [p.detach().clone() for p in trainer.pipeline.parameters()]
        record = trainer.train_step()
        handle.remove()
        assert math.isfinite(record["loss"]) and record["skipped"]
        assert record["bad_tensors"] == ["grad of grid[0] (1, 12, 12, 12)"]
        assert all(torch.equal(a, b) for a, b in zip(before, trainer.pipeline.parameters()))
        assert all(p.grad is None for p in trainer.pipeline.parameters())
        good = trainer.train_step()
        assert not good["skipped"] and not density.equal(before[0])


class RecordingVoxelGrid(register_backbone.VoxelGridBackbone):
    def after_step(self, step, features, optimizer):
        self.calls.append((step, features, optimizer, [p.grad is not None for p in self.parameters()]))


class TestStepRecord:
    def test_after_step_sees_the_step_the_features_and_the_gradients(self, tmp_path, voxel_scene, monkeypatch):
        trainer = voxel_trainer(tmp_path, voxel_scene)
        backbone = RecordingVoxelGrid(trainer.backbone.config, voxel_scene.scene_info())
        backbone.load_state_dict(trainer.backbone.state_dict())
        backbone.calls = []
        trainer.pipeline.backbone = backbone
        trainer.optimizer.param_groups[0]["params"] = list(backbone.parameters())
        features = []
        render = backbone.render_ldr_features
        monkeypatch.setattr(
            backbone, "render_ldr_features", lambda camera: features.append(render(camera)) or features[-1]
        )
        trainer.train_step()
        trainer.train_step()
        assert [call[0] for call in backbone.calls] == [0, 1]
        assert backbone.calls[1][1] is features[1] and backbone.calls[1][2] is trainer.optimizer
        assert all(all(has_grad) for *_, has_grad in backbone.calls)  # before the gradients are cleared

    def test_record_holds_floats_and_the_clipped_ldr_psnr(self, tmp_path):
        scene = known_scene()
        config = train_config_for(KnownRenderConfig)(
            backbone=KnownRenderConfig(brightness=1.6),
            out=tmp_path / "run",
            quiet=True,
            max_steps=3,
            save_renders=False,
        )
        trainer = Trainer(config, "known-render", scene)
        # the first epoch's order: a permutation from the run's seeded generator, taken from the end
        view = scene.train[torch.randperm(len(scene.train), generator=torch.Generator().manual_seed(0))[-1]]
        record = trainer.train_step()
        assert all(type(record[key]) is float for key in ("ldr", "hdr", "h2l", "loss", "ldr_psnr"))
        ldr, _ = expected_render(view.camera, "mono", brightness=1.6)
        expected = peak_signal_noise_ratio(view.image.double().numpy(), np.clip(ldr, 0, 1), data_range=1.0)
        assert record["ldr_psnr"] == pytest.approx(expected, rel=1e-5)


class TestEvaluateFromTheTrainer:
    def test_renders_only_when_asked(self, tmp_path, voxel_scene):
        trainer = voxel_trainer(tmp_path, voxel_scene, max_eval_views=1)
        metrics = trainer.evaluate()
        assert not (tmp_path / "run" / "renders").exists()
        assert (metrics["steps"], metrics["test_views"]) == (0, 1)
        trainer.evaluate(save_renders=True)
        assert sorted(p.name for p in (tmp_path / "run" / "renders").iterdir()) == [
            "view_001_hdr.exr",
            "view_001_hdr_mulaw.png",
            "view_001_ldr.png",
        ]
