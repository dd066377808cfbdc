"""Every script in benchmarks/ imports and answers --help (their long work is not run here), and the
arguments they share (mono_hdr_plugin.apps.bench.script_args) read and check values one way."""

import argparse
import math
import runpy
import sys
from pathlib import Path

import pytest

from mono_hdr_plugin.apps.bench import script_args

SCRIPTS = sorted((Path(__file__).parents[2] / "benchmarks").glob("*.py"))


@pytest.mark.parametrize("script", SCRIPTS, ids=[path.name for path in SCRIPTS])
def test_help(script, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", [str(script), "--help"])
    with pytest.raises(SystemExit) as exit_info:
        runpy.run_path(str(script), run_name="__main__")
    assert exit_info.value.code == 0
    assert "usage" in capsys.readouterr().out.lower()


def test_counts_are_checked_by_the_flag_rules():
    parser = script_args.script_parser("First paragraph.\n\nDetails.")
    script_args.add_count(parser, "--steps", 10)
    assert parser.description == "First paragraph." and parser.parse_args(["--steps", "3"]).steps == 3
    with pytest.raises(argparse.ArgumentTypeError, match="must be an integer >= 1, got 0"):
        script_args.COUNT("0")


def test_overrides_and_variants_read_like_bench_set():
    assert script_args.overrides(["hdr.converter_lr=0.002", "backbone.field.l2h_input=raw"]) == (
        ("hdr.converter_lr", 0.002),
        ("backbone.field.l2h_input", "raw"),
    )
    assert script_args.variant_overrides("base") == ()
    assert script_args.variant_overrides("occupancy_threshold=0.001,grid_size=64", "backbone.field.") == (
        ("backbone.field.occupancy_threshold", 0.001),
        ("backbone.field.grid_size", 64),
    )


class TestPlotCurves:
    """benchmarks/plot_curves.py: the finished rows of several bench curves folders in one plot."""

    @staticmethod
    def script():
        return runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "plot_curves.py"))

    def test_rows_of_every_folder_that_finished(self, tmp_path):
        import json

        for name, statuses in (("a", ["ok", "failed"]), ("b", ["ok"])):
            (tmp_path / name).mkdir()
            rows = {f"{name}{i}": {"status": status, "key": f"{name}{i}"} for i, status in enumerate(statuses)}
            (tmp_path / name / "curves.json").write_text(json.dumps({"rows": rows}))
        rows = self.script()["finished_rows"]([tmp_path / "a", tmp_path / "b"])
        assert [row["key"] for row in rows] == ["a0", "b0"]

    def test_a_folder_without_curves_names_the_command(self, tmp_path):
        with pytest.raises(SystemExit, match=r"missing/curves.json does not exist: run `mono-hdr bench curves"):
            self.script()["finished_rows"]([tmp_path / "missing"])


class TestPoseErrorGauge:
    """benchmarks/pose_refinement.py removes the gauge (a similarity of the whole rig) before it
    reports pose errors: a rig moved by a known similarity has none."""

    script = runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "pose_refinement.py"))

    def rig(self) -> list:
        import torch

        generator = torch.Generator().manual_seed(3)
        poses = []
        for _ in range(6):
            pose = torch.eye(4, dtype=torch.float64)
            pose[:3, :3] = self.script["so3_exp"](torch.randn(3, generator=generator, dtype=torch.float64))
            pose[:3, 3] = torch.randn(3, generator=generator, dtype=torch.float64)
            poses.append(pose)
        return poses

    def moved(self, poses: list, scale: float, axis_angle, translation) -> list:
        import torch

        rotation = self.script["so3_exp"](torch.tensor(axis_angle, dtype=torch.float64))
        moved = []
        for pose in poses:
            new = pose.clone()
            new[:3, :3] = rotation @ pose[:3, :3]
            new[:3, 3] = scale * rotation @ pose[:3, 3] + torch.tensor(translation, dtype=torch.float64)
            moved.append(new)
        return moved

    @pytest.mark.parametrize("gauge", ["centres", "poses"])
    def test_a_rig_moved_by_a_similarity_has_no_error(self, gauge):
        truth = self.rig()
        errors = self.script["pose_errors"](
            self.moved(truth, 2.5, [0.3, -0.2, 0.1], [1.0, 2.0, -3.0]), truth, 1.0, gauge
        )
        assert errors["rotation_degrees_max"] < 1e-6 and errors["translation_radius_max"] < 1e-9
        assert errors["alignment_scale"] == pytest.approx(1 / 2.5)
        assert errors["alignment_rotation_degrees"] == pytest.approx(math.degrees(math.sqrt(0.14)))

    def test_whole_poses_see_a_rotation_that_centres_miss(self):
        """Every camera turned by 1 degree about its own centre: the centres agree with the truth, so
        the centre fit keeps the turn as error; the whole-pose fit takes it as the rig's, error 0."""
        import torch

        truth = self.rig()
        turn = self.script["so3_exp"](torch.tensor([0.0, math.radians(1.0), 0.0], dtype=torch.float64))
        turned = [torch.cat([torch.cat([turn @ p[:3, :3], p[:3, 3:]], 1), p[3:]]) for p in truth]
        centres = self.script["pose_errors"](turned, truth, 1.0, "centres")
        assert centres["rotation_degrees_mean"] == pytest.approx(1.0, abs=1e-6)
        whole = self.script["pose_errors"](turned, truth, 1.0, "poses")
        assert whole["rotation_degrees_max"] < 1e-6
