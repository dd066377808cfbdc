"""A method registered from outside the package (examples/register_method.py) works everywhere."""

import json
import math

import pytest
import register_backbone
import register_method  # registers "tone-curve"
import torch
from helpers import quiet_config

from backbones.gs import GaussianConfig
from backbones.nerf import GridFieldConfig, NerfConfig
from mono_hdr_plugin.apps import cli
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.methods.base import METHODS, MethodConfig, build_method
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.resume import ResumeMismatch
from mono_hdr_plugin.training.trainer import Trainer, build_trainer

TINY_BACKBONES = {
    "gs": lambda: GaussianConfig(random_init_points=300),
    "nerf": lambda: NerfConfig(
        field=GridFieldConfig(
            levels=2,
            min_resolution=4,
            max_resolution=8,
            hidden_width=16,
            min_step=0.125,
            max_samples_per_ray=16,
            occupancy_resolution=8,
            rays_per_step=64,
            samples_per_step=512,
        )
    ),
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
        config = quiet_config(backbone_config, tmp_path / "run", "tone-curve", max_steps=2)
        trainer = Trainer(config, backbone, voxel_scene)
        before = trainer.method.raw_rises.detach().clone()
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) and not r["skipped"] and "hdr" in r for r in records)
        assert not torch.equal(before, trainer.method.raw_rises)


class TestItsOwnFlag:
    """--knots is declared by the example alone (ToneCurveOptions) and reaches the method through the CLI."""

    def test_the_flag_reaches_the_method(self, monkeypatch):
        import mono_hdr_plugin.training.trainer as trainer_module

        parsed = []
        monkeypatch.setattr(trainer_module, "run_training", lambda config, backbone: parsed.append(config))
        monkeypatch.setattr(cli, "print_metrics", lambda *args: None)
        cli.command_train(["voxel-grid", "--method", "tone-curve", "--knots", "5", "--scene", "demo"])
        assert parsed[0].hdr.options == register_method.ToneCurveOptions(knots=5)
        method = build_method(parsed[0].hdr, "mse")
        assert method.knots == 5 and method.raw_rises.shape == (4,)

    def test_help_of_the_method_lists_it(self, capsys):
        with pytest.raises(SystemExit) as exit_info:
            main(["train", "voxel-grid", "--method", "tone-curve", "--help"])
        assert exit_info.value.code == 0
        help_text = capsys.readouterr().out
        assert "--knots" in help_text and "Knots of the piecewise-linear" in help_text
        with pytest.raises(SystemExit):
            main(["train", "voxel-grid", "--help"])
        assert "--knots" not in capsys.readouterr().out

    def test_without_the_method_the_flag_is_refused_naming_it(self, tmp_path):
        with pytest.raises(FlagError, match="^--knots is a flag of --method tone-curve, not of --method mono"):
            main(["train", "voxel-grid", "--knots", "5", "--scene", "demo", "--out", str(tmp_path / "run")])
        with pytest.raises(FlagError, match="--knots must be an integer >= 2, got 1"):
            main(
                [
                    "train",
                    "voxel-grid",
                    "--method",
                    "tone-curve",
                    "--knots",
                    "1",
                    "--scene",
                    "demo",
                    "--out",
                    str(tmp_path / "run"),
                ]
            )

    def test_a_resume_keeps_the_knots_it_declares(self, tmp_path, voxel_scene):
        def trainer(knots: int, resume: bool) -> Trainer:
            config = train_config_for(register_backbone.VoxelGridConfig, "tone-curve")(
                backbone=TINY_BACKBONES["voxel-grid"](),
                out=tmp_path / "run",
                quiet=True,
                save_renders=False,
                max_steps=1,
                resume=resume,
            )
            config.hdr.options.knots = knots
            return build_trainer(config, "voxel-grid", voxel_scene)

        assert "--knots" in register_method.GlobalToneCurve.resume_identity_flags
        trainer(8, resume=False).save()
        with pytest.raises(ResumeMismatch, match="it was trained with --knots 8, not 5"):
            trainer(5, resume=True)
        assert trainer(8, resume=True).method.knots == 8

    def test_its_export_recipe_is_its_own(self):
        assert "knots" in register_method.GlobalToneCurve.hdr_recipe


class TestCommandLine:
    def test_train_eval_round_trip(self, tmp_path):
        out = tmp_path / "run"
        main(
            [
                "train",
                "voxel-grid",
                "--method",
                "tone-curve",
                "--scene",
                "demo",
                "--max-steps",
                "3",
                "--out",
                str(out),
                "--quiet",
                "--max-eval-views",
                "2",
                "--backbone.resolution",
                "8",
                "--backbone.samples-per-ray",
                "8",
                "--no-save-renders",
            ]
        )
        trained = json.loads((out / "metrics.json").read_text())
        assert trained["method"] == "tone-curve"
        main(
            [
                "eval",
                "--checkpoint",
                str(out / "checkpoints" / "latest.pt"),
                "--out",
                str(tmp_path / "eval"),
                "--no-save-renders",
            ]
        )
        again = json.loads((tmp_path / "eval" / "metrics.json").read_text())
        assert again["hdr_psnr"] == pytest.approx(trained["hdr_psnr"], rel=1e-6)
