"""Every script in benchmarks/ imports and answers --help (their long work is not run here), and the
arguments they share (mono_hdr_plugin.apps.bench.script_args) read and check values one way."""

import argparse
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
