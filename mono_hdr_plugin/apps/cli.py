"""The `mono-hdr` command line (tyro). Each command is a config dataclass plus a function.

`run` is the console entry point and the one place where a user's error (bad flag, bad data, a
file-system fault, an unusable checkpoint or output folder) becomes one line on stderr and exit
code 2, and Ctrl-C exit code 130 (with the command that resumes an interrupted training).
"""

import os
import shlex
import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro
from rich.console import Console
from rich.table import Table
from rich.text import Text

from mono_hdr_plugin.core.validation import FlagError, check_flags

console = Console()
errors = Console(stderr=True, soft_wrap=True)
EVAL_OUTPUTS = ("metrics.json", "renders")


@dataclass
class EvalConfig:
    """Evaluate a checkpoint on the test views and write OUT/metrics.json (and renders)."""

    checkpoint: Path
    """A checkpoint written by `mono-hdr train` (OUT/checkpoints/latest.pt)."""
    out: Path = Path("outputs/eval")
    """Folder for metrics.json and renders/."""
    data: Path | None = None
    """Evaluate on this dataset folder instead of the run's own data (same protocol settings)."""
    scene: str | None = None
    """Evaluate on this built-in scene instead of the run's own data."""
    save_renders: bool = True
    """Write EXR and PNG renders of the test views."""
    overwrite: bool = False
    """Replace an earlier evaluation's metrics.json and renders/ in --out instead of refusing."""


@dataclass
class BackbonesConfig:
    """List every backbone with where it came from."""


@dataclass
class PresetChoice:
    """The first pass of `mono-hdr train`: the preset gives the defaults of the second, the method its flags."""

    preset: str | None = None
    method: str | None = None


def command_train(argv: list[str]) -> None:
    from mono_hdr_plugin.core.registry import BACKBONES
    from mono_hdr_plugin.training.config import train_config_for
    from mono_hdr_plugin.training.trainer import run_training

    backbones = BACKBONES.available()
    # A preset changes the defaults of other flags and a method brings flags of its own, so tyro parses them first.
    choice, _ = tyro.cli(
        PresetChoice,
        args=[a for a in argv if a not in ("-h", "--help")],
        return_unknown_args=True,
        prog="mono-hdr train",
    )
    refuse_flags_of_other_methods(argv, choice.method)
    backbone_arg = next((a for a in argv if a in backbones), None)
    defaults = {}
    for name, entry in backbones.items():
        presets = entry.plugin.presets()
        preset = choice.preset if name == backbone_arg and choice.preset is not None else next(iter(presets))
        if preset not in presets:
            raise ValueError(
                f"--preset {preset!r} is not a preset of backbone {name!r}; choose one of "
                f"{', '.join(presets)} (listed by `mono-hdr backbones`)"
            )
        defaults[name] = train_config_for(entry.plugin.config_class, choice.method)(
            backbone=presets[preset], preset=preset
        )
    described = {name: (_first_line(backbones[name].plugin.__doc__), default) for name, default in defaults.items()}
    config = tyro.extras.overridable_config_cli(
        described, args=argv, prog="mono-hdr train", description="Train a backbone with Mono-HDR or a baseline."
    )
    backbone_name = next(name for name, default in defaults.items() if type(default) is type(config))
    if config.viewer:
        from mono_hdr_plugin.apps.viewer.live_training import train_with_viewer

        def report(metrics: dict) -> None:
            print_metrics(metrics, config.out / "metrics.json")

        run_training(config, backbone_name, lambda trainer: train_with_viewer(trainer, report))
        return
    metrics = run_training(config, backbone_name)
    print_metrics(metrics, config.out / "metrics.json")


def refuse_flags_of_other_methods(argv: list[str], method: str | None) -> None:
    """A flag of another method's own options (`--unit-exposure-weight` without `--method hdr-nerf`) is
    named with the methods that take it, instead of tyro's bare "unrecognized argument"."""
    from mono_hdr_plugin.methods.base import METHODS, MethodConfig

    chosen = MethodConfig.method if method is None else method
    own = set(METHODS.get(chosen).own_flags())
    for flag in {arg.split("=", 1)[0] for arg in argv if arg.startswith("--")} - own:
        owners = [name for name, entry in METHODS.available().items() if flag in entry.plugin.own_flags()]
        if owners:
            raise FlagError(
                f"{flag} is a flag of --method {' / '.join(owners)}, not of --method {chosen}: pass "
                f"--method {owners[0]} with it, or leave it out"
            )


def _first_line(text: str | None) -> str:
    return (text or "").strip().splitlines()[0] if (text or "").strip() else ""


def command_eval(config: EvalConfig) -> None:
    from mono_hdr_plugin.data.io import write_json
    from mono_hdr_plugin.data.outputs import check_output, claim_output
    from mono_hdr_plugin.training.evaluation import evaluate
    from mono_hdr_plugin.training.trained import load_trained_model

    claim: dict[str, Any] = {"command": "eval", "owned": EVAL_OUTPUTS, "overwrite": config.overwrite}
    check_output(config.out, inputs=[config.checkpoint], **claim)  # before the slow load
    run = load_trained_model(config.checkpoint, data_path=config.data, scene_name=config.scene)
    with claim_output(config.out, inputs=[config.checkpoint, run.config.data.data], **claim) as output:
        output.clear_previous()
        metrics = evaluate(
            run.pipeline,
            run.scene,
            run.config.max_eval_views,
            render_dir=config.out / "renders" if config.save_renders else None,
            eval_appearance=run.config.exposure.eval_appearance,
            eval_pose=run.config.camera.eval_pose,
        )
        metrics.update(preset=run.config.preset, steps=run.step, train_seconds=run.train_seconds)
        write_json(config.out / "metrics.json", metrics)
    print_metrics(metrics, config.out / "metrics.json")


def command_render(config: Any) -> None:
    """`mono-hdr render` in a folder it claims: one writer at a time, never a folder another command or a
    person wrote; renders add to an earlier render's folder (files of the same name are replaced)."""
    from mono_hdr_plugin.apps.render import check_render_flags, render_command
    from mono_hdr_plugin.data.outputs import claim_output

    check_render_flags(config)  # before the output folder is claimed
    with claim_output(config.out, "render", None, inputs=[config.checkpoint], keep=True):
        render_command(config)


def command_bench(argv: list[str]) -> None:
    import mono_hdr_plugin.apps.bench  # noqa: F401 - registers the built-in benchmarks
    from mono_hdr_plugin.core.registry import BENCHMARKS

    benchmarks: dict[str, Any] = {name: entry.plugin for name, entry in BENCHMARKS.available().items()}
    config = tyro.extras.subcommand_cli_from_dict(
        benchmarks,
        args=argv,
        prog="mono-hdr bench",
        description="Accuracy versus time: curves, the paper's tables, cost against image size and views, and "
        "what plugins contribute (3DGS: raster).",
    )
    check_flags(config)
    config.out.mkdir(parents=True, exist_ok=True)
    config.run()


def command_backbones(config: BackbonesConfig) -> None:
    from mono_hdr_plugin.core.backbone import Backbone
    from mono_hdr_plugin.core.registry import BACKBONES

    def describe(cls: type[Backbone]) -> tuple[str, ...]:
        return (
            ", ".join(cls.presets()),
            cls.loss_kind,
            "whole image" if cls.pixel_batch is None else str(cls.pixel_batch),
        )

    print_plugins(BACKBONES, "mono-hdr backbones", ("presets (first: default)", "loss", "rays per step"), describe)


@dataclass
class MethodsConfig:
    """List every method (--method) with where it came from."""


def command_methods(config: MethodsConfig) -> None:
    from mono_hdr_plugin.methods.base import METHODS, HdrMethod

    def describe(cls: type[HdrMethod]) -> tuple[str]:
        flags = cls.own_flags()
        return (_first_line(cls.__doc__) + (f"\nits own flags: {', '.join(flags)}" if flags else ""),)

    print_plugins(METHODS, "mono-hdr methods (--method)", ("what it is",), describe)


@dataclass
class LayoutsConfig:
    """List every dataset layout (--layout) with where it came from."""


def command_layouts(config: LayoutsConfig) -> None:
    from mono_hdr_plugin.data.layouts import LAYOUTS

    print_plugins(
        LAYOUTS,
        "mono-hdr layouts (--layout; detected in this order)",
        ("files", "writable"),
        lambda cls: (cls.description, "yes" if cls.writable else "no"),
    )


def print_plugins(registry, title: str, columns: tuple[str, ...], describe: Callable[[Any], tuple[str, ...]]) -> None:
    """A table of a registry's plugins (name, class, source, then `describe(plugin)`), broken ones in red."""
    table = Table(title=title)
    for column in ("name", "class", "source", *columns):
        table.add_column(column)
    for name, entry in registry.available().items():
        plugin = entry.plugin
        table.add_row(
            *(
                Text(str(cell))
                for cell in (name, f"{plugin.__module__}.{plugin.__qualname__}", entry.source, *describe(plugin))
            )
        )
    for name, reason in registry.broken().items():  # plain Text: an error message is not markup
        table.add_row(Text(name, style="red"), Text("broken", style="red"), Text(reason), *[""] * len(columns))
    console.print(table)


def print_metrics(metrics: dict, path: Path) -> None:
    from mono_hdr_plugin.core.calibration import RadianceCalibration
    from mono_hdr_plugin.training.evaluation import HDR_KEYS, RADIANCE_KEYS

    table = Table(
        title=Text(
            f"{metrics['backbone']} / {metrics['method']} on {metrics['scene']} "
            f"({metrics['steps']} steps, {metrics['train_seconds']:.0f} s)"
        )
    )
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key in (*HDR_KEYS, "ldr_psnr", "ldr_ssim"):
        value = metrics.get(key)
        table.add_row(key, "n/a (no HDR ground truth)" if value is None else f"{value:.4f}")
    for key in RADIANCE_KEYS:
        value = metrics.get(key)
        table.add_row(key, "n/a (too few well-exposed pixels)" if value is None else f"{value:.4f}")
    if "radiance_scale" in metrics:
        calibration = RadianceCalibration(metrics["radiance_scale"], metrics["radiance_units"])
        table.add_row("HDR calibration", Text(calibration.describe()))
    if "hdr_basis" in metrics:
        table.add_row("HDR rests on", Text(metrics["hdr_basis"]))
    for exposure, value in metrics["ldr_psnr_per_exposure"].items():
        table.add_row(f"ldr_psnr @ {exposure} s", f"{value:.4f}")
    console.print(table)
    for warning in metrics.get("hdr_warnings", []):
        note = f" {warning} (docs/method.md, 'Scores without ground truth')"
        errors.print(Text.assemble(("warning:", "bold yellow"), note))
    console.print(Text(f"metrics written to {path}"), soft_wrap=True)


def _commands() -> dict[str, tuple[str, Callable[[list[str]], None]]]:
    """name -> (help line, runner taking the remaining argv)."""

    def simple(config_class: type, function: Callable, prog: str) -> tuple[str, Callable[[list[str]], None]]:
        def parse_check_run(argv: list[str]) -> None:
            config: Any = tyro.cli(config_class, args=argv, prog=f"mono-hdr {prog}", description=config_class.__doc__)
            check_flags(config)
            function(config)

        return config_class.__doc__ or "", parse_check_run

    commands = {
        "train": ("train <backbone>: train a model (see `mono-hdr train --help`)", command_train),
        "eval": simple(EvalConfig, command_eval, "eval"),
        "backbones": simple(BackbonesConfig, command_backbones, "backbones"),
        "methods": simple(MethodsConfig, command_methods, "methods"),
        "layouts": simple(LayoutsConfig, command_layouts, "layouts"),
        "bench": ("bench curves|paper|raster: what accuracy costs in time (JSON, Markdown, plots)", command_bench),
    }
    for name, (config_class, function) in _application_commands().items():
        commands[name] = simple(config_class, function, name)
    return commands


def _application_commands() -> dict[str, tuple[type, Callable]]:
    """Commands of the studio, viewing and process-data modules (imported only when the command line
    is built; a broken import shows as the error it is, not as a missing command)."""
    from mono_hdr_plugin.apps.export import ExportConfig, export_command
    from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data_command
    from mono_hdr_plugin.apps.render import RenderConfig
    from mono_hdr_plugin.apps.studio.commands import ScenesConfig, SynthConfig, list_scenes_command, synth
    from mono_hdr_plugin.apps.viewer.command import ViewConfig, view_command

    return {
        "render": (RenderConfig, command_render),
        "view": (ViewConfig, view_command),
        "export": (ExportConfig, export_command),
        "scenes": (ScenesConfig, list_scenes_command),
        "synth": (SynthConfig, synth),
        "process-data": (ProcessDataConfig, process_data_command),
    }


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    commands = _commands()
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in commands:
        console.print("usage: mono-hdr COMMAND [options]   (mono-hdr COMMAND --help for its options)\n")
        for name, (help_line, _) in commands.items():
            console.print(f"  [bold]{name:<12}[/bold] {help_line.strip().splitlines()[0]}")
        if argv and argv[0] not in ("-h", "--help"):
            console.print(f"\n[red]unknown command {argv[0]!r}")
            raise SystemExit(2)
        return
    commands[argv[0]][1](argv[1:])


def resume_command(argv: list[str]) -> str:
    """The command line that continues an interrupted `mono-hdr train` run."""
    kept = [arg for arg in argv if arg not in ("--resume", "--no-resume", "--overwrite", "--no-overwrite")]
    return shlex.join(["mono-hdr", *kept, "--resume"])


def error_line(error: BaseException) -> str:
    """A user error as one line: its message (lines joined), or for a bare file-system error the path,
    what went wrong and the fix."""
    from mono_hdr_plugin.data.errors import DatasetError, os_error_line

    text = os_error_line(error) if isinstance(error, OSError) and not isinstance(error, DatasetError) else str(error)
    return " ".join(line.strip() for line in text.splitlines() if line.strip()) or type(error).__name__


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as one plain line on stderr, `warning: ...`: the user needs its message, not the
    module and source line that raised it (MONO_HDR_DEBUG=1 keeps Python's format)."""
    text = " ".join(part.strip() for part in str(message).splitlines() if part.strip())
    errors.print(Text.assemble(("warning:", "bold yellow"), f" {text}"), highlight=False)


def run() -> None:
    """Console entry point: user errors print one line and exit 2 (set MONO_HDR_DEBUG=1 for the
    traceback); Ctrl-C exits 130, after training with the command that resumes it; warnings are
    one line each."""
    from mono_hdr_plugin.core.registry import RegistryError
    from mono_hdr_plugin.data.outputs import OutputError
    from mono_hdr_plugin.training.checkpoints import CheckpointError
    from mono_hdr_plugin.training.hooks import TrainingInterrupted
    from mono_hdr_plugin.training.trainer import TrainingDiverged

    if not os.environ.get("MONO_HDR_DEBUG"):
        warnings.showwarning = show_warning
    try:
        main()
    except KeyboardInterrupt as interrupt:
        if os.environ.get("MONO_HDR_DEBUG"):
            raise
        if isinstance(interrupt, TrainingInterrupted):
            errors.print(Text(f"{interrupt}. Resume with: {resume_command(sys.argv[1:])}"), highlight=False)
        else:
            errors.print(Text("interrupted"), highlight=False)
        raise SystemExit(130) from None
    except (ValueError, OSError, CheckpointError, OutputError, RegistryError, TrainingDiverged) as error:
        if os.environ.get("MONO_HDR_DEBUG"):
            raise
        errors.print(Text.assemble(("error:", "bold red"), f" {error_line(error)}"), highlight=False)
        raise SystemExit(2) from None


if __name__ == "__main__":
    run()
