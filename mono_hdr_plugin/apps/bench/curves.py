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
    parse_presets,
)
from mono_hdr_plugin.core.registry import register_benchmark
from mono_hdr_plugin.core.validation import POSITIVE, at_least, between


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
    exposure_index: int = 1
    """0, 1, 2: the single training exposure t1, t3, t5."""
    budget_seconds: float | None = None
    """Training seconds per run (default 60 quick, 600 full)."""
    eval_points: int = 5
    """Evaluations along each run."""
    max_eval_views: int | None = None
    """Test views per evaluation (default 4 quick, all full)."""
    executor: Annotated[ExecutorConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=ExecutorConfig)
    """Where the runs execute."""

    flag_rules: ClassVar = {
        "exposure_index": between(0, 2),
        "budget_seconds": POSITIVE,
        "eval_points": at_least(1),
        "max_eval_views": at_least(1),
    }

    def run(self) -> dict[str, Any]:
        return bench_curves(self)


def curve_specs(config: BenchCurvesConfig) -> list[RunSpec]:
    backbones = config.backbones or tuple(paper_backbones().values())
    presets = parse_presets(config.presets)
    return [
        RunSpec(backbone=b, method=m, preset=presets.get(b), scene=s, exposure_index=config.exposure_index)
        for s in config.scenes
        for b in backbones
        for m in config.methods
    ]


def bench_curves(config: BenchCurvesConfig) -> dict[str, Any]:
    budget = RunBudget(
        seconds=config.budget_seconds or (60.0 if config.quick else 600.0),
        eval_points=config.eval_points,
        max_eval_views=config.max_eval_views or (4 if config.quick else None),
    )
    specs = curve_specs(config)
    store = RowStore(config.out / "curves.json", {"budget": budget.__dict__, "specs": [s.key for s in specs]})
    with report_on_exit(lambda: write_curves_report(store, config.out)):
        execute(specs, budget, store, config.out / "runs", config.executor)
    return {"facts": store.facts, "rows": store.rows}


def write_curves_report(store: RowStore, out: Path) -> None:
    rows = [row for row in store.rows.values() if row["status"] == "ok"]
    lines = [
        "| scene | backbone / method | steps | seconds | ms / step | HDR PSNR | HDR PSNR (GT max) | HDR SSIM "
        "| LDR PSNR | LDR SSIM | fps LDR | fps LDR+HDR | HDR render cost | Gaussians | peak MiB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in sorted(rows, key=lambda r: (r["spec"]["scene"], label(r["spec"]))):
        final = row["final"]
        lines.append(
            f"| {row['spec']['scene']} | {label(row['spec'])} | {final['steps']} | {final['train_seconds']:.0f} | "
            f"{1000 * row['mean_step_seconds']:.1f} | {fmt(final['hdr_psnr'])} | {fmt(final['hdr_psnr_gt_max'])} | "
            f"{fmt(final['hdr_ssim'], 3)} | {fmt(final['ldr_psnr'])} | {fmt(final['ldr_ssim'], 3)} | "
            f"{row['fps_ldr']:.1f} | {row['fps_ldr_hdr']:.1f} | {row['fps_ldr'] / row['fps_ldr_hdr']:.3f}x | "
            f"{row['backbone_statistics'].get('gaussians', '')} | {row['peak_memory_mib']:.0f} |"
        )
    failed = [row for row in store.rows.values() if row["status"] != "ok"]
    lines += [f"\nFailed: {row['key']}: {row['error']}" for row in failed]
    out.mkdir(parents=True, exist_ok=True)
    (out / "curves.md").write_text("\n".join(lines) + "\n")
    if rows:
        plot_curves(rows, out / "curves.png")


def plot_curves(rows: list[dict], path: Path) -> None:
    """One row of panels per scene: HDR and LDR PSNR against training seconds, a line per backbone/method."""
    plt = pyplot()
    scenes = sorted({row["spec"]["scene"] for row in rows})
    threads = sorted({row["threads"] for row in rows if "threads" in row})
    plural = "" if threads == [1] else "s"
    seconds_label = (
        f"training seconds ({' or '.join(map(str, threads))} torch thread{plural} a run)"
        if threads
        else "training seconds"
    )
    figure, axes = plt.subplots(len(scenes), 2, figsize=(11, 3.6 * len(scenes)), squeeze=False)
    for axes_row, scene in zip(axes, scenes):
        for row in sorted((r for r in rows if r["spec"]["scene"] == scene), key=lambda r: label(r["spec"])):
            seconds = [point["train_seconds"] for point in row["curve"]]
            for axis, key in zip(axes_row, ("hdr_psnr", "ldr_psnr")):
                axis.plot(seconds, [point[key] for point in row["curve"]], marker="o", label=label(row["spec"]))
        for axis, title in zip(axes_row, ("HDR mu-law PSNR (dB)", "LDR PSNR (dB)")):
            axis.set_title(f"{scene}: {title}")
            axis.set_xlabel(seconds_label)
            axis.grid(alpha=0.3)
        axes_row[0].legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
