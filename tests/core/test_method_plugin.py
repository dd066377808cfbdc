"""A method registered from outside the package (examples/register_method.py) works everywhere."""

import json
import math

import pytest
import torch

import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
import register_method  # registers "tone-curve"
from backbones.gs import GaussianConfig
from backbones.nerf import GridFieldConfig, NerfConfig
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.methods import METHODS, MethodConfig, build_method
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer

TINY_BACKBONES = {
    "gs": lambda: GaussianConfig(random_init_points=300),
    "nerf": lambda: NerfConfig(field=GridFieldConfig(
        levels=2, min_resolution=4, max_resolution=8, hidden_width=16, min_step=0.125, max_samples_per_ray=16,
        occupancy_resolution=8, rays_per_step=64, samples_per_step=512)),
    "voxel-grid": lambda: register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24),
}


class TestRegistration:
    def test_registered_from_outside_with_its_source(self):
        entry = METHODS.available()["tone-curve"]
        assert entry.plugin is register_method.GlobalToneCurve and entry.source == "python: register_method"

    def test_listed_by_the_command(self, capsys):
        main(["methods"])
        out = capsys.readouterr().out
        assert "tone-curve" in out and "register_method" in out and "hdr-gs" in out


class TestToneCurve:
    def test_starts_as_the_straight_line_in_log_space(self):
        method = build_method(MethodConfig(method="tone-curve"), "mse")
        values = method.log_curve(torch.tensor([0.0, 0.5, 1.0, 1.0 / 15]))
        torch.testing.assert_close(values, torch.tensor([-4.0, 0.0, 4.0, -4.0 + 8.0 / 15]))

    def test_stays_monotone_whatever_the_parameters(self):
        method = build_method(MethodConfig(method="tone-curve"), "mse")
        with torch.no_grad():
            method.raw_rises.normal_(0, 5)
        values = method.log_curve(torch.linspace(0, 1, 301))
        assert (values[1:] >= values[:-1]).all()


@pytest.mark.parametrize("backbone", sorted(TINY_BACKBONES))
class TestTrainsOnEveryBackbone:
    def test_two_steps_move_the_curve(self, tmp_path, voxel_scene, backbone):
        backbone_config = TINY_BACKBONES[backbone]()
        config = train_config_for(type(backbone_config))(backbone=backbone_config, out=tmp_path / "run", quiet=True,
                                                         save_renders=False, checkpoint_every=10**9, max_steps=2)
        config.hdr.method = "tone-curve"
        trainer = Trainer(config, backbone, voxel_scene)
        before = trainer.method.raw_rises.detach().clone()
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] and "hdr" in r for r in records)
        assert not torch.equal(before, trainer.method.raw_rises)


class TestCommandLine:
    def test_train_eval_round_trip(self, tmp_path):
        out = tmp_path / "run"
        main(["train", "voxel-grid", "--method", "tone-curve", "--scene", "demo", "--max-steps", "3", "--out",
              str(out), "--quiet", "--max-eval-views", "2", "--backbone.resolution", "8",
              "--backbone.samples-per-ray", "8", "--no-save-renders"])
        trained = json.loads((out / "metrics.json").read_text())
        assert trained["method"] == "tone-curve"
        main(["eval", "--checkpoint", str(out / "checkpoints" / "latest.pt"), "--out", str(tmp_path / "eval"),
              "--no-save-renders"])
        again = json.loads((tmp_path / "eval" / "metrics.json").read_text())
        assert again["hdr_psnr"] == pytest.approx(trained["hdr_psnr"], rel=1e-6)
