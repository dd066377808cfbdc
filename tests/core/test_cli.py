"""The mono-hdr command line, driven as a user would (tiny runs of the example backbone)."""

import json

import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)

from backbones.nerf import GridFieldConfig, MlpFieldConfig
from mono_hdr_plugin.apps.cli import main


class TestHelp:
    def test_top_level_lists_commands(self, capsys):
        main(["--help"])
        out = capsys.readouterr().out
        for command in ("train", "eval", "render", "backbones"):
            assert command in out

    def test_unknown_command_exits_2(self, capsys):
        with pytest.raises(SystemExit) as exit_info:
            main(["bogus"])
        assert exit_info.value.code == 2

    @pytest.mark.parametrize(
        "argv", [["train", "--help"], ["train", "voxel-grid", "--help"], ["eval", "--help"], ["render", "--help"]]
    )
    def test_every_help_is_readable(self, argv, capsys):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 0
        assert "usage" in capsys.readouterr().out.lower()

    def test_train_help_shows_common_flags(self, capsys):
        with pytest.raises(SystemExit):
            main(["train", "voxel-grid", "--help"])
        out = capsys.readouterr().out
        for flag in ("--data", "--scene", "--method", "--max-steps", "--out", "--resume", "--seed"):
            assert flag in out

    def test_bench_help_lists_every_registered_benchmark(self, capsys):
        with pytest.raises(SystemExit) as exit_info:
            main(["bench", "--help"])
        assert exit_info.value.code == 0
        out = capsys.readouterr().out
        assert "{cost,curves,paper,raster}" in out


class TestBackbonesCommand:
    def test_lists_example_with_source(self, capsys):
        main(["backbones"])
        out = capsys.readouterr().out
        assert "voxel-grid" in out and "python" in out


class TestTrainEvalRender:
    def test_train_then_eval_then_render(self, tmp_path):
        out = tmp_path / "run"
        main(
            [
                "train",
                "voxel-grid",
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
            ]
        )
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["steps"] == 3 and metrics["backbone"] == "voxel-grid" and metrics["method"] == "mono"
        assert list(out.glob("renders/*_hdr.exr")) and list(out.glob("renders/*_ldr.png"))

        checkpoint = out / "checkpoints" / "latest.pt"
        main(
            [
                "eval",
                "--checkpoint",
                str(checkpoint),
                "--out",
                str(tmp_path / "eval"),
                "--no-save-renders",
                "--scene",
                "demo",
            ]
        )
        again = json.loads((tmp_path / "eval" / "metrics.json").read_text())
        assert again["ldr_psnr"] == pytest.approx(metrics["ldr_psnr"], rel=1e-5)

        main(
            [
                "render",
                "--checkpoint",
                str(checkpoint),
                "--out",
                str(tmp_path / "render"),
                "--exposures",
                "0.5",
                "8",
                "--max-views",
                "1",
            ]
        )
        names = sorted(p.name for p in (tmp_path / "render").iterdir())
        assert any(n.endswith("_hdr.exr") for n in names)
        assert any(n.endswith("_ldr_0.5s.png") for n in names) and any(n.endswith("_ldr_8s.png") for n in names)

    def test_resume_continues_from_checkpoint(self, tmp_path):
        out = tmp_path / "run"
        common = [
            "--scene",
            "demo",
            "--out",
            str(out),
            "--quiet",
            "--max-eval-views",
            "1",
            "--backbone.resolution",
            "8",
            "--backbone.samples-per-ray",
            "8",
            "--no-save-renders",
        ]
        main(["train", "voxel-grid", "--max-steps", "2", *common])
        main(["train", "voxel-grid", "--max-steps", "4", "--resume", *common])
        assert json.loads((out / "metrics.json").read_text())["steps"] == 4


class TestConsoleEntry:
    def test_user_error_is_one_line_and_exit_2(self, monkeypatch, capsys):
        from mono_hdr_plugin.apps import cli

        monkeypatch.setattr("sys.argv", ["mono-hdr", "eval", "--checkpoint", "/nonexistent/latest.pt"])
        monkeypatch.delenv("MONO_HDR_DEBUG", raising=False)
        with pytest.raises(SystemExit) as exit_info:
            cli.run()
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert "error:" in err and "latest.pt does not exist" in err and "Traceback" not in err
        assert len(err.strip().splitlines()) == 1


class TestPresets:
    @pytest.fixture
    def captured(self, monkeypatch):
        """The config `mono-hdr train` would train, without training."""
        import mono_hdr_plugin.training.trainer as train_module

        seen = {}

        def capture(config, backbone_name):
            seen["config"], seen["backbone"] = config, backbone_name
            raise SystemExit(0)

        monkeypatch.setattr(train_module, "run_training", capture)
        return seen

    def test_preset_gives_the_defaults_and_flags_override_it(self, captured):
        with pytest.raises(SystemExit):
            main(["train", "nerf", "--preset", "paper", "--backbone.field.coarse-samples", "16"])
        config = captured["config"]
        assert captured["backbone"] == "nerf" and config.preset == "paper"
        assert isinstance(config.backbone.field, MlpFieldConfig) and config.backbone.field.coarse_samples == 16

    def test_default_preset_is_the_first(self, captured):
        from backbones.nerf import NerfBackbone

        with pytest.raises(SystemExit):
            main(["train", "nerf", "--backbone.field.max-resolution", "64"])
        config = captured["config"]
        assert config.preset == next(iter(NerfBackbone.presets())) == "cpu"
        assert isinstance(config.backbone.field, GridFieldConfig) and config.backbone.field.max_resolution == 64

    def test_the_preset_alone_chooses_the_nerf_field(self):
        """One way to choose the field: the cpu preset has no paper-field flags (and no --backbone.field.X choice)."""
        with pytest.raises(SystemExit):
            main(["train", "nerf", "--backbone.field.coarse-samples", "16"])

    def test_unknown_preset_names_the_choices(self):
        with pytest.raises(ValueError, match="not a preset of backbone 'nerf'.*paper"):
            main(["train", "nerf", "--preset", "slow"])

    def test_backbones_lists_presets(self, capsys):
        main(["backbones"])
        assert "paper" in capsys.readouterr().out
