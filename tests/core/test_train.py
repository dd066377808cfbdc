"""The training loop end to end with the example voxel-grid backbone (tiny, seconds)."""

import json
import math

import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
import torch
from helpers import FakeClock, quiet_config

from mono_hdr_plugin.methods.base import method_names
from mono_hdr_plugin.training.checkpoints import CheckpointError, load_checkpoint, save_checkpoint
from mono_hdr_plugin.training.config import hdr_supervised_views, parse_view_ratio
from mono_hdr_plugin.training.evaluation import evaluate
from mono_hdr_plugin.training.frames import calibrate
from mono_hdr_plugin.training.trained import load_trained_model
from mono_hdr_plugin.training.trainer import Trainer


def make_config(tmp_path, backbone_config, method: str = "mono", **overrides):
    config = quiet_config(backbone_config, tmp_path / "run", method)
    for key, value in overrides.items():
        if hasattr(config.hdr, key):
            setattr(config.hdr, key, value)
        else:
            setattr(config, key, value)
    return config


class TestHdrViewRatio:
    @pytest.mark.parametrize("ratio,count", [("1:1", 9), ("2:1", 5), ("3:1", 3), ("5:1", 2), ("1:0", 0), ("0:1", 9)])
    def test_counts(self, ratio, count):
        assert sum(hdr_supervised_views(9, ratio)) == count

    @pytest.mark.parametrize("bad", ["2", "a:b", "0:0", "-1:1"])
    def test_bad_ratio_names_the_flag(self, bad):
        with pytest.raises(ValueError, match="--hdr-view-ratio"):
            parse_view_ratio(bad)


class TestTwoStepsOfEveryMethod:
    @pytest.mark.parametrize("method", method_names())
    def test_two_steps(self, tmp_path, voxel_scene, voxel_backbone_config, method):
        trainer = Trainer(
            make_config(tmp_path, voxel_backbone_config, method=method, max_steps=2), "voxel-grid", voxel_scene
        )
        before = [p.detach().clone() for p in trainer.backbone.parameters()]
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] for r in records)
        assert any(not torch.equal(a, b) for a, b in zip(before, trainer.backbone.parameters()))

    def test_converters_are_optimised(self, tmp_path, voxel_scene, voxel_backbone_config):
        trainer = Trainer(make_config(tmp_path, voxel_backbone_config), "voxel-grid", voxel_scene)
        optimised = {id(p) for g in trainer.optimizer.param_groups for p in g["params"]}
        assert all(id(p) in optimised for p in trainer.method.h2l.parameters())
        assert all(id(p) in optimised for p in trainer.method.l2h.parameters())


class TestCheckpoints:
    def test_resume_gives_same_next_loss(self, tmp_path, voxel_scene, voxel_backbone_config):
        config = make_config(tmp_path, voxel_backbone_config, max_steps=6)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        for _ in range(3):
            trainer.train_step()
        trainer.save()
        expected = trainer.train_step()["loss"]
        resumed = Trainer(config, "voxel-grid", voxel_scene)
        resumed.restore(load_checkpoint(trainer.checkpoint_path()))
        assert resumed.step == 3
        assert resumed.train_step()["loss"] == pytest.approx(expected, rel=1e-6)

    def test_other_version_is_refused_with_clear_error(self, tmp_path):
        path = tmp_path / "old.pt"
        save_checkpoint(path, {"step": 1})
        payload = torch.load(path, weights_only=True)
        payload["format_version"] = 99
        torch.save(payload, path)
        with pytest.raises(CheckpointError, match="format version 99"):
            load_checkpoint(path)

    def test_missing_and_truncated(self, tmp_path):
        with pytest.raises(CheckpointError, match="does not exist"):
            load_checkpoint(tmp_path / "nope.pt")
        path = tmp_path / "cut.pt"
        save_checkpoint(path, {"step": 1, "weights": torch.zeros(1000)})
        path.write_bytes(path.read_bytes()[:200])
        with pytest.raises(CheckpointError, match="cannot be read"):
            load_checkpoint(path)

    def test_no_temporary_files_left(self, tmp_path):
        save_checkpoint(tmp_path / "a.pt", {"step": 1})
        assert [p.name for p in tmp_path.iterdir()] == ["a.pt"]


class TestNanGuard:
    def test_bad_step_skipped_then_training_stops(self, tmp_path, voxel_scene, voxel_backbone_config, monkeypatch):
        from mono_hdr_plugin.training.trainer import TrainingDiverged

        trainer = Trainer(
            make_config(tmp_path, voxel_backbone_config, max_steps=50, nan_patience=3), "voxel-grid", voxel_scene
        )
        trainer.save()
        good = [p.detach().clone() for p in trainer.backbone.parameters()]
        original = trainer.method.losses
        monkeypatch.setattr(trainer.method, "losses", lambda *a: {k: v * float("nan") for k, v in original(*a).items()})
        with pytest.raises(TrainingDiverged, match="3 consecutive steps.*latest.pt"):
            trainer.train()
        assert all(torch.equal(a, b) for a, b in zip(good, trainer.backbone.parameters()))


class TestEndToEnd:
    def test_example_backbone_hdr_error_drops(self, tmp_path, voxel_scene, voxel_backbone_config):
        config = make_config(tmp_path, voxel_backbone_config, max_steps=150)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        before = trainer.evaluate()
        after = trainer.train()
        assert after["hdr_psnr"] > before["hdr_psnr"] + 3.0
        assert after["ldr_psnr"] > before["ldr_psnr"] + 3.0
        written = json.loads((config.out / "metrics.json").read_text())
        for key in (
            "hdr_psnr",
            "hdr_ssim",
            "ldr_psnr",
            "ldr_ssim",
            "ldr_psnr_per_exposure",
            "train_seconds",
            "steps",
            "backbone",
            "method",
        ):
            assert key in written
        assert written["steps"] == 150 and written["backbone"] == "voxel-grid"

    def test_load_trained_model_restores_and_evaluates(self, tmp_path, voxel_scene, voxel_backbone_config):
        config = make_config(tmp_path, voxel_backbone_config, max_steps=5)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        metrics = trainer.train()
        run = load_trained_model(trainer.checkpoint_path(), scene=voxel_scene)
        assert run.step == 5 and not run.pipeline.training
        assert evaluate(run.pipeline, run.scene)["hdr_psnr"] == pytest.approx(metrics["hdr_psnr"], rel=1e-5)

    def test_loaded_model_fits_its_exposure_model_only_when_asked(self, tmp_path, voxel_scene, voxel_backbone_config):
        """Eval needs no display scale: loading renders nothing; render, view and export fit it once."""
        config = make_config(tmp_path, voxel_backbone_config, max_steps=3)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        trainer.train()
        run = load_trained_model(trainer.checkpoint_path(), scene=voxel_scene)
        assert "exposure" not in vars(run) and run.train_seconds == pytest.approx(trainer.train_seconds)
        trainer.pipeline.eval()
        assert run.exposure == calibrate(trainer.pipeline, voxel_scene) and run.exposure is run.exposure


class TestSceneExtent:
    def test_single_camera_falls_back_to_scene_diagonal(self, voxel_scene):
        info = voxel_scene.scene_info()
        info.train_cameras = info.train_cameras[:1]
        expected = 0.5 * float((info.bounds_max - info.bounds_min).norm())
        assert info.extent == pytest.approx(expected)

    def test_rig_radius_with_several_cameras(self, voxel_scene):
        info = voxel_scene.scene_info()
        centers = torch.stack([c.center for c in info.train_cameras])
        assert info.extent == pytest.approx(1.1 * float((centers - centers.mean(0)).norm(dim=-1).max()))


class TestTimeBudget:
    @pytest.fixture
    def half_second_steps(self, monkeypatch):
        import mono_hdr_plugin.training.trainer as train_module

        clock = FakeClock(0.5)
        monkeypatch.setattr(train_module.time, "perf_counter", clock.perf_counter)
        return clock

    def test_stops_at_max_seconds_and_scales_schedules(
        self, tmp_path, voxel_scene, voxel_backbone_config, half_second_steps
    ):
        config = make_config(tmp_path, voxel_backbone_config, max_steps=1000, max_seconds=10.0)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        assert trainer.backbone.max_steps == 1000
        metrics = trainer.train()
        assert metrics["steps"] == 20 and metrics["train_seconds"] == pytest.approx(10.0)
        assert trainer.run_length == 20 and trainer.backbone.max_steps == 20

    def test_max_steps_ends_first(self, tmp_path, voxel_scene, voxel_backbone_config, half_second_steps):
        config = make_config(tmp_path, voxel_backbone_config, max_steps=8, max_seconds=100.0)
        assert Trainer(config, "voxel-grid", voxel_scene).train()["steps"] == 8

    def test_resume_keeps_the_budget_and_the_schedule(
        self, tmp_path, voxel_scene, voxel_backbone_config, half_second_steps
    ):
        config = make_config(tmp_path, voxel_backbone_config, max_steps=1000, max_seconds=10.0)
        trainer = Trainer(config, "voxel-grid", voxel_scene)
        for _ in range(12):
            trainer.train_step()
        trainer.save()
        resumed = Trainer(config, "voxel-grid", voxel_scene)
        resumed.restore(load_checkpoint(trainer.checkpoint_path()))
        assert resumed.backbone.max_steps == 20 and resumed.train_seconds == pytest.approx(6.0)
        assert resumed.train()["steps"] == 20

    @pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
    def test_bad_budget_names_the_flag(self, tmp_path, voxel_scene, voxel_backbone_config, bad):
        with pytest.raises(ValueError, match="--max-seconds"):
            Trainer(make_config(tmp_path, voxel_backbone_config, max_seconds=bad), "voxel-grid", voxel_scene)
