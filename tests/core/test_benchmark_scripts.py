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
