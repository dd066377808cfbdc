"""`mono-hdr bench curves`: quality versus training seconds, each backbone x method x scene."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, ClassVar

import tyro

from mono_hdr_plugin.apps.bench.report import fmt, label, pyplot, report_on_exit
from mono_hdr_plugin.apps.bench.runs import (
    ExecutorConfig,
    RowStore,
    RunBudget,
    RunSpec,
    execute,
    paper_backbones,
    parse_override,
    parse_presets,
)
from mono_hdr_plugin.core.registry import register_benchmark
from mono_hdr_plugin.core.validation import POSITIVE, at_least, between
from mono_hdr_plugin.data.config import TRAINING_RESOLUTION


@register_benchmark("curves")
@dataclass
class BenchCurvesConfig:
    """Quality versus training time for each backbone x method x scene (one seed, exposure t3)."""

    out: Path = Path("benchmarks/results")
    """Folder for curves.json, curves.md and the plots."""
    quick: bool = False
    """A size that finishes in minutes on 2 cores."""
    backbones: tuple[str, ...] = ()
    """Backbones to compare (default: every backbone that reproduces one of the paper's)."""
    methods: tuple[str, ...] = ("mono", "hdr-gs", "hdr-nerf")
    """Methods to compare."""
    presets: tuple[str, ...] = ()
    """BACKBONE=PRESET pairs (`mono-hdr backbones` lists presets); others run their default preset."""
    scenes: tuple[str, ...] = ("demo",)
    """Studio scenes."""
    set: tuple[str, ...] = ()
    """PATH=VALUE overrides of every run's config on top of the preset, as the benchmark scripts' --set
    (e.g. pyramid_levels=3, backbone.lr_sh_dc=0.0025); they are part of each row's key and label."""
    resolution: int | None = None
    """Studio scene size, N x N pixels (default: the scenes' own 128; a size not yet rendered is rendered
    first, once, cached)."""
    exposure_index: int = 1
    """0, 1, 2: the single training exposure t1, t3, t5."""
    budget_seconds: float | None = None
    """Training seconds per run (default 60 quick, 600 full)."""
    budget_steps: int | None = None
    """Optimiser steps per run instead of seconds: figures that do not depend on the machine's load
    (the x axis stays training seconds, which do). With --budget-seconds too, whichever ends first."""
    eval_points: int = 5
    """Evaluations along each run."""
    max_eval_views: int | None = None
    """Test views per evaluation (default 4 quick, all full)."""
    executor: Annotated[ExecutorConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=ExecutorConfig)
    """Where the runs execute."""

    flag_rules: ClassVar = {
        "exposure_index": between(0, 2),
        "resolution": TRAINING_RESOLUTION,
        "budget_seconds": POSITIVE,
        "budget_steps": at_least(1),
        "eval_points": at_least(1),
        "max_eval_views": at_least(1),
    }

    def run(self) -> dict[str, Any]:
        return bench_curves(self)


def curve_specs(config: BenchCurvesConfig) -> list[RunSpec]:
    backbones = config.backbones or tuple(paper_backbones().values())
    presets = parse_presets(config.presets)
    overrides = tuple(parse_override(text) for text in config.set)
    return [
        RunSpec(
            backbone=b,
            method=m,
            preset=presets.get(b),
            scene=s,
            exposure_index=config.exposure_index,
            resolution=config.resolution,
            overrides=overrides,
        )
        for s in config.scenes
        for b in backbones
        for m in config.methods
    ]


def bench_curves(config: BenchCurvesConfig) -> dict[str, Any]:
    default_seconds = None if config.budget_steps else (60.0 if config.quick else 600.0)
    budget = RunBudget(
        seconds=config.budget_seconds or default_seconds,
        steps=config.budget_steps,
        eval_points=config.eval_points,
        max_eval_views=config.max_eval_views or (4 if config.quick else None),
    )
    specs = curve_specs(config)
    store = RowStore(config.out / "curves.json", {"budget": budget.__dict__})
    with report_on_exit(lambda: write_curves_report(store, config.out)):
        execute(specs, budget, store, config.out / "runs", config.executor)
    return {"facts": store.facts, "rows": store.rows}


def write_curves_report(store: RowStore, out: Path) -> None:
    rows = [row for row in store.rows.values() if row["status"] == "ok"]
    lines = [
        "| scene | backbone / method | steps | seconds | ms / step | HDR PSNR | HDR PSNR (GT max) | GT max, masked "
        "| GT max, aligned | median ratio | GT max fell | scale spread | peak ratio | worst peak | chroma outliers "
        "| HDR SSIM | LDR PSNR | LDR SSIM | fps LDR "
        "| fps LDR+HDR | HDR render cost | Gaussians | peak MiB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in sorted(rows, key=lambda r: (r["spec"]["scene"], label(r["spec"]))):
        final = row["final"]
        lines.append(
            f"| {row['spec']['scene']} | {label(row['spec'])} | {final['steps']} | {final['train_seconds']:.0f} | "
            f"{1000 * row['mean_step_seconds']:.1f} | {fmt(final['hdr_psnr'])} | {fmt(final['hdr_psnr_gt_max'])} | "
            f"{fmt(final.get('hdr_psnr_masked'))} | {fmt(final.get('hdr_psnr_aligned'))} | "
            f"{fmt(final.get('hdr_median_ratio'), 3)} | {fmt(gt_max_fall(row['curve']))} | "
            f"{fmt(scale_spread(row['curve']), 3)} | {fmt(final.get('hdr_peak_ratio'), 2)} | "
            f"{fmt(final.get('hdr_peak_ratio_worst'), 2)} | {fmt(final.get('chroma_outliers'), 4)} | "
            f"{fmt(final['hdr_ssim'], 3)} | {fmt(final['ldr_psnr'])} | "
            f"{fmt(final['ldr_ssim'], 3)} | {row['fps_ldr']:.1f} | {row['fps_ldr_hdr']:.1f} | "
            f"{row['fps_ldr'] / row['fps_ldr_hdr']:.3f}x | {row['backbone_statistics'].get('gaussians', '')} | "
            f"{row['peak_memory_mib']:.0f} |"
        )
    failed = [row for row in store.rows.values() if row["status"] != "ok"]
    lines += [f"\nFailed: {row['key']}: {row['error']}" for row in failed]
    lines += [
        "",
        "GT max fell: the largest drop of the GT-max HDR PSNR below its best earlier value along the curve (dB).",
        "Scale spread: max / min - 1 of the radiance scale fitted at the evaluations of the second half of the run.",
        "Median ratio: calibrated HDR / ground truth over pixels the test photo exposes well (1 is exact).",
        "Peak ratio: the calibrated HDR's peak on the brightest source (sun, bulb) over the ground truth's, mean over "
        "views; worst peak: the view farthest from 1 (near 0: the source is lost).",
        "Chroma outliers: fraction of well-exposed pixels whose chromaticity is off by more than 0.05 "
        "(coloured floaters).",
        "Peak MiB: the process's resident peak from the row's start (its scene, loaded once per process, counts).",
    ]
    out.mkdir(parents=True, exist_ok=True)
    (out / "curves.md").write_text("\n".join(lines) + "\n")
    if rows:
        plot_curves(rows, out / "curves.png")


def gt_max_fall(curve: list[dict]) -> float | None:
    """The largest drop of the GT-max HDR PSNR below its best earlier value (0: it never fell)."""
    if any(point.get("hdr_psnr_gt_max") is None for point in curve):
        return None
    values: list[float] = [point["hdr_psnr_gt_max"] for point in curve]
    return max((max(values[: i + 1]) - value for i, value in enumerate(values)), default=0.0)


def scale_spread(curve: list[dict]) -> float | None:
    """max / min - 1 of the radiance scales fitted over the second half of the curve's evaluations."""
    half = curve[len(curve) // 2 :]
    if not half or any(point.get("radiance_scale") is None for point in half):
        return None
    scales: list[float] = [point["radiance_scale"] for point in half]
    return max(scales) / min(scales) - 1.0


PANELS = (
    ("hdr_psnr", "HDR PSNR (dB, mu-law, own max)"),
    ("hdr_psnr_gt_max", "HDR PSNR (dB, GT max; dashed: emitters masked)"),
    ("ldr_psnr", "LDR PSNR (dB)"),
)


def plot_curves(rows: list[dict], path: Path) -> None:
    """One row of panels per scene: HDR (own max; GT max, calibrated, and emitter-masked dashed) and LDR
    PSNR against training seconds, a line per backbone/method."""
    plt = pyplot()
    scenes = sorted({row["spec"]["scene"] for row in rows})
    threads = sorted({row["threads"] for row in rows if "threads" in row})
    plural = "" if threads == [1] else "s"
    seconds_label = (
        f"training seconds ({' or '.join(map(str, threads))} torch thread{plural} a run)"
        if threads
        else "training seconds"
    )
    # a run keeps its colour in every scene's panels
    labels = sorted({label(row["spec"]) for row in rows})
    colours = {name: f"C{index % 10}" for index, name in enumerate(labels)}
    figure, axes = plt.subplots(len(scenes), len(PANELS), figsize=(15, 3.6 * len(scenes)), squeeze=False)
    for axes_row, scene in zip(axes, scenes):
        for row in sorted((r for r in rows if r["spec"]["scene"] == scene), key=lambda r: label(r["spec"])):
            seconds = [point["train_seconds"] for point in row["curve"]]
            name = label(row["spec"])
            for axis, (key, _) in zip(axes_row, PANELS):
                values = [point[key] for point in row["curve"]]
                line = axis.plot(seconds, values, marker="o", label=name, color=colours[name])
                if key == "hdr_psnr_gt_max" and all(point.get("hdr_psnr_masked") for point in row["curve"]):
                    masked = [point["hdr_psnr_masked"] for point in row["curve"]]
                    axis.plot(seconds, masked, linestyle="--", color=line[0].get_color())
        for axis, (_, title) in zip(axes_row, PANELS):
            axis.set_title(f"{scene}: {title}", fontsize=9)
            axis.set_xlabel(seconds_label)
            axis.grid(alpha=0.3)
        axes_row[0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
