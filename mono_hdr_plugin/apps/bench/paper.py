"""`mono-hdr bench paper`: the paper's tables on the built-in scenes, at a training-time budget per
run, over seeds and exposures, next to the paper's figures; and the fair-recipe question.

Every row is a (variant, scene, exposure, seed) run of `runs.run_row`. A variant's figure on a
scene is the mean over seeds of its per-seed value (the mean over exposures); the spread is the
standard deviation over seeds. Averaged over scenes, a seed's value is its mean over scenes and
exposures. An ordering of two variants counts as REPRODUCED only when it has the paper's sign
and the gap between the means exceeds the sum of the two spreads; a gap within the spreads is a
TIE, and a gap beyond them the other way is REVERSED. With one seed there is no spread, and the
report says so.
"""

import itertools
import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import tyro

from mono_hdr_plugin.apps.bench.report import fmt, pyplot, report_on_exit
from mono_hdr_plugin.apps.bench.runs import (
    ExecutorConfig,
    RowStore,
    RunBudget,
    RunSpec,
    console,
    execute,
    paper_backbones,
    parse_presets,
)
from mono_hdr_plugin.core.registry import get_backbone, register_benchmark
from mono_hdr_plugin.core.validation import POSITIVE, SEED, FlagError, at_least, between

# The paper's figures (docs/method.md), HDR PSNR in dB, by the paper's backbone rows; a registered
# backbone reproduces a row through its `paper_backbone`. The ablations are the paper's 3DGS ones.
PAPER_BASELINE = {"NeRF": "hdr-nerf", "3DGS": "hdr-gs"}
PAPER_TABLE1 = {
    ("NeRF", "hdr-nerf"): 13.76,
    ("NeRF", "mono"): 32.86,
    ("3DGS", "hdr-gs"): 35.30,
    ("3DGS", "mono"): 38.57,
}
PAPER_TABLE1_LDR = {
    ("NeRF", "hdr-nerf"): 30.62,
    ("NeRF", "mono"): 38.78,
    ("3DGS", "hdr-gs"): 39.48,
    ("3DGS", "mono"): 41.68,
}
PAPER_CONVERTERS = {"mlp-l2h": 19.02, "mlp-h2l": 38.43, "no-h2l": 38.19, "mono": 38.57}
LOSS_ROWS = {  # name -> (L_ldr, L_hdr, L_h2l), paper figure (None: "fails to train", no figure)
    "ldr": ((True, False, False), None),
    "hdr": ((False, True, False), 33.93),
    "h2l": ((False, False, True), 11.87),
    "ldr+hdr": ((True, True, False), 38.19),
    "ldr+h2l": ((True, False, True), 13.50),
    "hdr+h2l": ((False, True, True), 33.58),
    "ldr+hdr+h2l": ((True, True, True), 38.57),
}
PAPER_RATIOS = {
    "mono": {"1:1": 38.57, "2:1": 37.97, "3:1": 37.53, "5:1": 35.51, "0:1": 33.93, "1:0": 13.50},
    "hdr-gs": {"1:1": 35.30, "2:1": 35.26, "3:1": 35.16, "5:1": 34.89, "0:1": 33.46, "1:0": 10.51},
}
# The fair-recipe table tunes these method settings for every method alike, times the backbone's
# own `tuning_space()`: every method gets the same number of trials.
METHOD_TUNING_SPACE = {"hdr.converter_lr": (5e-4, 2e-3)}
TableName = Literal["table1", "converters", "losses", "ratios", "recipes"]
METRICS = ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "ldr_psnr", "ldr_ssim")


@register_benchmark("paper")
@dataclass
class BenchPaperConfig:
    """The paper's tables re-run on studio scenes (single exposure), over seeds, next to its figures.

    The defaults are the full grid (every built-in scene, t1/t3/t5, 3 seeds, every table): meant
    for a Ray cluster. `--quick` is a minutes-long check.
    """

    out: Path = Path("benchmarks/results")
    """Folder for paper.json, paper.md and the plots."""
    quick: bool = False
    """Minutes on 2 cores: demo, t3, 2 seeds, Table 1 only, 20 steps a run."""
    scenes: tuple[str, ...] = ("demo", "lamp-room", "sunlit-window", "glossy", "coloured-light")
    """Studio scenes the tables are reported on (and averaged over)."""
    exposure_indices: tuple[int, ...] = (0, 1, 2)
    """Single training exposures t1/t3/t5 (0, 1, 2); a seed's figure is the mean over them."""
    seeds: tuple[int, ...] = (0, 1, 2)
    """Seeds of the Table 1 and recipe rows (mean +- standard deviation over them)."""
    ablation_seeds: tuple[int, ...] = (0, 1, 2)
    """Seeds of the converter, loss and ratio ablations."""
    ablation_scenes: tuple[str, ...] | None = None
    """Scenes of the ablations (default: the same as --scenes)."""
    budget_seconds: float | None = 300.0
    """Training seconds per run (evaluation not counted)."""
    steps: int | None = None
    """Optimiser steps per run; with --budget-seconds, whichever ends first. Steps alone make
    rows reproducible to the bit (the executors' equality test uses them)."""
    eval_points: int = 4
    """Evaluations along each run (the Table 1 curves); the last is the row's result."""
    max_eval_views: int | None = None
    """Test views per evaluation (default: all)."""
    tables: tuple[TableName, ...] = ("table1", "converters", "losses", "ratios", "recipes")
    """Which tables to run."""
    tune_scene: str = "demo"
    """The recipe table tunes each method here and reports it on the OTHER scenes of --scenes."""
    presets: tuple[str, ...] = ()
    """BACKBONE=PRESET pairs; other backbones run their default (CPU) preset."""
    executor: Annotated[ExecutorConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=ExecutorConfig)
    """Where the runs execute."""

    flag_rules: ClassVar = {
        "exposure_indices": between(0, 2),
        "seeds": SEED,
        "ablation_seeds": SEED,
        "budget_seconds": POSITIVE,
        "steps": at_least(1),
        "eval_points": at_least(1),
        "max_eval_views": at_least(1),
    }

    def run(self) -> dict[str, Any]:
        return bench_paper(self)

    def resolved(self) -> "BenchPaperConfig":
        """--quick applied."""
        if not self.quick:
            return self
        return BenchPaperConfig(
            out=self.out,
            scenes=("demo",),
            exposure_indices=(1,),
            seeds=(0, 1),
            ablation_seeds=(0,),
            budget_seconds=None,
            steps=20,
            eval_points=1,
            max_eval_views=2,
            tables=("table1",),
            presets=self.presets,
            executor=self.executor,
        )


@dataclass(frozen=True)
class Variant:
    """One row of a table: what is trained (without scene, exposure and seed) and the paper's figure."""

    table: str
    name: str
    spec: RunSpec
    paper_hdr_psnr: float | None = None
    paper_ldr_psnr: float | None = None
    seeds: tuple[int, ...] = (0,)
    scenes: tuple[str, ...] = ()

    def runs(self, exposures: tuple[int, ...]) -> list[RunSpec]:
        return [
            RunSpec(**{**self.spec.__dict__, "scene": scene, "exposure_index": exposure, "seed": seed})
            for scene in self.scenes
            for exposure in exposures
            for seed in self.seeds
        ]


def table_variants(config: BenchPaperConfig) -> list[Variant]:
    """Every variant of the fixed tables (not the tuned recipes), on the backbones reproducing the paper's."""
    backbones, presets = paper_backbones(), parse_presets(config.presets)
    ablation_scenes = config.ablation_scenes or config.scenes

    def spec(row: str, method: str, **options) -> RunSpec:
        return RunSpec(backbones[row], method, preset=presets.get(backbones[row]), **options)

    variants = []
    if "table1" in config.tables or "recipes" in config.tables:  # the recipe table's shared-recipe rows
        variants += [
            Variant(
                "table1",
                f"{row} {method}",
                spec(row, method),
                PAPER_TABLE1[(row, method)],
                PAPER_TABLE1_LDR[(row, method)],
                config.seeds,
                config.scenes,
            )
            for row in PAPER_BASELINE
            if row in backbones
            for method in (PAPER_BASELINE[row], "mono")
        ]

    def ablation(table: str, name: str, row_spec: RunSpec, figure: float | None) -> Variant:
        return Variant(table, name, row_spec, figure, seeds=config.ablation_seeds, scenes=ablation_scenes)

    if "3DGS" in backbones:
        if "converters" in config.tables:
            variants += [ablation("converters", m, spec("3DGS", m), PAPER_CONVERTERS[m]) for m in PAPER_CONVERTERS]
        if "losses" in config.tables:
            variants += [
                ablation("losses", name, spec("3DGS", "mono", losses=switches), figure)
                for name, (switches, figure) in LOSS_ROWS.items()
            ]
        if "ratios" in config.tables:
            variants += [
                ablation("ratios", f"{m} {r}", spec("3DGS", m, hdr_view_ratio=r), PAPER_RATIOS[m][r])
                for m in ("mono", "hdr-gs")
                for r in PAPER_RATIOS[m]
            ]
    return variants


def tuning_trials(config: BenchPaperConfig) -> dict[tuple[str, str], list[RunSpec]]:
    """(paper row, method) -> the same number of recipe trials for every method, on the tune scene."""
    backbones, presets = paper_backbones(), parse_presets(config.presets)
    trials = {}
    for row, backbone in backbones.items():
        backbone_class = get_backbone(backbone)
        preset_configs = backbone_class.presets()
        chosen = presets.get(backbone)  # a name parse_presets checked; else the first preset, the default
        preset_config = preset_configs[chosen] if chosen is not None else next(iter(preset_configs.values()))
        space = {f"backbone.{path}": values for path, values in backbone_class.tuning_space(preset_config).items()}
        space |= METHOD_TUNING_SPACE
        grid = [tuple(zip(space, values)) for values in itertools.product(*space.values())]
        for method in (PAPER_BASELINE[row], "mono"):
            trials[(row, method)] = [
                RunSpec(
                    backbone,
                    method,
                    preset=presets.get(backbone),
                    scene=config.tune_scene,
                    exposure_index=config.exposure_indices[len(config.exposure_indices) // 2],
                    overrides=overrides,
                )
                for overrides in grid
            ]
    return trials


def bench_paper(config: BenchPaperConfig) -> dict[str, Any]:
    config = config.resolved()
    budget = RunBudget(
        seconds=config.budget_seconds,
        steps=config.steps,
        eval_points=config.eval_points,
        max_eval_views=config.max_eval_views,
    )
    variants = table_variants(config)
    trials = tuning_trials(config) if "recipes" in config.tables else {}
    report_scenes = tuple(s for s in config.scenes if s != config.tune_scene)
    if trials and not report_scenes:
        raise FlagError(
            f"the recipe table reports on scenes other than --tune-scene {config.tune_scene!r}: "
            "add another scene to --scenes"
        )
    specs = list(dict.fromkeys(spec for v in variants for spec in v.runs(config.exposure_indices)))
    trial_specs = [spec for specs_of in trials.values() for spec in specs_of]
    settings = {"budget": budget.__dict__, "exposure_indices": list(config.exposure_indices)}
    store = RowStore(config.out / "paper.json", settings)
    planned = (
        len(specs)
        + len(trial_specs)
        + len(trials) * len(report_scenes) * len(config.exposure_indices) * len(config.seeds)
    )
    cpus = config.executor.cpus_per_run or (1 if config.executor.executor == "ray" else 2)
    if budget.seconds is not None:
        console.print(
            f"bench paper: {planned} runs x {budget.seconds:.0f} s x {cpus} CPU = "
            f"{planned * budget.seconds * cpus / 3600:.1f} CPU-hours of training (plus evaluation)"
        )
    recipes: dict[tuple[str, str], dict] = {}
    with report_on_exit(lambda: write_paper_report(config, variants, recipes, store)):
        execute(specs + trial_specs, budget, store, config.out / "runs", config.executor)
        if trials:
            recipes.update(best_recipes(trials, store))
            best_variants = [
                Variant("recipes", f"{row} {method} tuned", recipe["spec"], seeds=config.seeds, scenes=report_scenes)
                for (row, method), recipe in recipes.items()
            ]
            execute(
                [s for v in best_variants for s in v.runs(config.exposure_indices)],
                budget,
                store,
                config.out / "runs",
                config.executor,
            )
    return {"facts": store.facts, "rows": store.rows, "recipes": recipes}


def best_recipes(trials: dict[tuple[str, str], list[RunSpec]], store: RowStore) -> dict[tuple[str, str], dict]:
    """The trial with the highest HDR PSNR (own max, the paper's headline metric) of each method."""
    best = {}
    for key, specs in trials.items():
        scored = [
            (store.rows[s.key]["final"]["hdr_psnr"], s)
            for s in specs
            if store.rows.get(s.key, {}).get("status") == "ok"
        ]
        if scored:
            score, spec = max(scored, key=lambda item: item[0])
            best[key] = {
                "spec": RunSpec(**{**spec.__dict__, "scene": "", "exposure_index": 0}),
                "overrides": dict(spec.overrides),
                "tune_hdr_psnr": score,
                "trials": len(specs),
            }
    return best


# ----------------------------------------------------------------------------- aggregation
def seed_values(
    variant: Variant, store: RowStore, exposures: tuple[int, ...], metric: str, scenes: tuple[str, ...] | None = None
) -> dict[int, float]:
    """seed -> the metric averaged over `scenes` (default: the variant's) and the exposures; seeds
    with a failed or missing run are left out."""
    values = {}
    for seed in variant.seeds:
        runs = [
            store.rows.get(RunSpec(**{**variant.spec.__dict__, "scene": s, "exposure_index": e, "seed": seed}).key)
            for s in (scenes or variant.scenes)
            for e in exposures
        ]
        finished = [r for r in runs if r is not None and r["status"] == "ok" and r["final"][metric] is not None]
        if runs and len(finished) == len(runs):
            values[seed] = statistics.fmean(r["final"][metric] for r in finished)
    return values


def mean_spread(values: dict[int, float]) -> tuple[float | None, float | None]:
    """Mean and standard deviation over seeds (spread 0 with one seed, None with none)."""
    if not values:
        return None, None
    numbers = list(values.values())
    return statistics.fmean(numbers), statistics.stdev(numbers) if len(numbers) > 1 else 0.0


def ordering(ours_a: tuple[float, float], ours_b: tuple[float, float], paper_a: float, paper_b: float) -> str:
    """reproduced / tie / reversed, by the rule in this module's docstring."""
    (mean_a, spread_a), (mean_b, spread_b) = ours_a, ours_b
    gap = mean_a - mean_b
    if abs(gap) <= spread_a + spread_b:
        return "tie"
    return "reproduced" if (gap > 0) == (paper_a > paper_b) else "reversed"


def summarise(variants: list[Variant], store: RowStore, exposures: tuple[int, ...]) -> list[dict[str, Any]]:
    """Per variant: mean +- spread of each metric averaged over its scenes, and per scene HDR PSNR."""
    rows = []
    for variant in variants:
        row: dict[str, Any] = {
            "table": variant.table,
            "variant": variant.name,
            "backbone": variant.spec.backbone,
            "paper_hdr_psnr": variant.paper_hdr_psnr,
            "paper_ldr_psnr": variant.paper_ldr_psnr,
            "seeds": len(variant.seeds),
            "scenes": list(variant.scenes),
        }
        for metric in METRICS:
            row[metric] = mean_spread(seed_values(variant, store, exposures, metric))
        row["per_scene_hdr_psnr"] = {
            scene: mean_spread(seed_values(variant, store, exposures, "hdr_psnr", (scene,))) for scene in variant.scenes
        }
        rows.append(row)
    return rows


def orderings(rows: list[dict[str, Any]]) -> list[tuple[str, str, str]]:
    """(a, b, verdict) for every pair of rows of one table that both have a paper figure and a result."""
    usable = [r for r in rows if r["paper_hdr_psnr"] is not None and r["hdr_psnr"][0] is not None]
    verdicts = []
    for a, b in itertools.combinations(usable, 2):
        if a["paper_hdr_psnr"] != b["paper_hdr_psnr"]:
            verdicts.append(
                (
                    a["variant"],
                    b["variant"],
                    ordering(a["hdr_psnr"], b["hdr_psnr"], a["paper_hdr_psnr"], b["paper_hdr_psnr"]),
                )
            )
    return verdicts


# ---------------------------------------------------------------------------------- report
def _pm(value: tuple[float | None, float | None], digits: int = 2) -> str:
    mean, spread = value
    return "n/a" if mean is None else f"{mean:.{digits}f} +- {spread:.{digits}f}"


def write_paper_report(config: BenchPaperConfig, variants: list[Variant], recipes: dict, store: RowStore) -> None:
    exposures = config.exposure_indices
    rows = summarise(variants, store, exposures)
    budget = store.settings["budget"]
    lines = [
        f"git {store.facts['git_commit'][:10]}; budget per run: "
        f"{fmt(budget['seconds'], 0)} s / {budget['steps'] or '-'} steps; exposures "
        f"{', '.join(f't{2 * e + 1}' for e in exposures)} averaged; mean +- standard deviation over seeds. "
        "An ordering is reproduced when its sign matches the paper's and the gap exceeds the sum of "
        "the two spreads (tie: within them; reversed: beyond them, the other way).",
        "",
    ]
    for table in dict.fromkeys(v.table for v in variants):
        table_rows = [r for r in rows if r["table"] == table]
        scenes = table_rows[0]["scenes"]
        lines += [
            f"### {table} (scenes: {', '.join(scenes)}; {table_rows[0]['seeds']} seed(s))",
            "",
            "| variant | HDR PSNR | paper HDR PSNR | HDR PSNR (GT max) | HDR SSIM | LDR PSNR | LDR SSIM | "
            + " | ".join(f"HDR PSNR {s}" for s in scenes)
            + " |",
            "|---" * (7 + len(scenes)) + "|",
        ]
        for r in table_rows:
            lines.append(
                f"| {r['variant']} | {_pm(r['hdr_psnr'])} | {fmt(r['paper_hdr_psnr'])} | "
                f"{_pm(r['hdr_psnr_gt_max'])} | {_pm(r['hdr_ssim'], 3)} | {_pm(r['ldr_psnr'])} | "
                f"{_pm(r['ldr_ssim'], 3)} | " + " | ".join(_pm(r["per_scene_hdr_psnr"][s]) for s in scenes) + " |"
            )
        verdicts = orderings(table_rows)
        counts = {v: sum(1 for *_, verdict in verdicts if verdict == v) for v in ("reproduced", "tie", "reversed")}
        lines += [
            "",
            f"Orderings against the paper's: {counts['reproduced']} reproduced, {counts['tie']} ties, "
            f"{counts['reversed']} reversed of {len(verdicts)} pairs.",
        ]
        lines += [f"- {a} vs {b}: {verdict}" for a, b, verdict in verdicts if verdict != "reproduced"]
        lines.append("")
    if recipes:
        lines += recipe_lines(config, variants, recipes, store)
    failed = [row for row in store.rows.values() if row["status"] != "ok"]
    lines += [f"Failed run {row['key']}: {row['error']}" for row in failed]
    config.out.mkdir(parents=True, exist_ok=True)
    (config.out / "paper.md").write_text("\n".join(lines) + "\n")
    table1 = [r for r in rows if r["table"] == "table1"]
    if table1 and any(r["hdr_psnr"][0] is not None for r in table1):
        plot_table1(table1, config.out / "paper_table1.png")
        plot_table1_curves(
            [v for v in variants if v.table == "table1"], store, exposures, config.out / "paper_curves.png"
        )


def recipe_lines(config: BenchPaperConfig, variants: list[Variant], recipes: dict, store: RowStore) -> list[str]:
    """Shared CPU recipe against each method's own tuned recipe, on the scenes it was NOT tuned on."""
    exposures = config.exposure_indices
    report_scenes = tuple(s for s in config.scenes if s != config.tune_scene)
    lines = [
        f"### recipes: shared CPU recipe vs each method's own best (tuned on {config.tune_scene}, "
        f"reported on {', '.join(report_scenes)})",
        "",
        "| backbone method | trials | tuned settings | HDR PSNR shared | HDR PSNR own | LDR PSNR shared | "
        "LDR PSNR own |",
        "|---|---|---|---|---|---|---|",
    ]
    table1 = {v.name: v for v in variants if v.table == "table1"}
    for (row, method), recipe in recipes.items():
        shared = table1.get(f"{row} {method}")
        tuned = Variant("recipes", "", recipe["spec"], seeds=config.seeds, scenes=report_scenes)
        cells = []
        for metric in ("hdr_psnr", "ldr_psnr"):
            cells.append(
                _pm(mean_spread(seed_values(shared, store, exposures, metric, report_scenes))) if shared else "n/a"
            )
            cells.append(_pm(mean_spread(seed_values(tuned, store, exposures, metric))))
        settings = ", ".join(f"{path}={value:g}" for path, value in recipe["overrides"].items())
        lines.append(
            f"| {row} {method} | {recipe['trials']} | {settings} | {cells[0]} | {cells[1]} | {cells[2]} | {cells[3]} |"
        )
    return lines + [""]


def plot_table1(rows: list[dict], path: Path) -> None:
    """Bars of HDR and LDR PSNR (mean over scenes, error bars: spread over seeds), paper figures as markers."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(10, 4))
    names = [r["variant"] for r in rows]
    for axis, metric, paper_key, title in (
        (axes[0], "hdr_psnr", "paper_hdr_psnr", "HDR PSNR (dB, mu-law, own max)"),
        (axes[1], "ldr_psnr", "paper_ldr_psnr", "LDR PSNR (dB)"),
    ):
        means = [r[metric][0] if r[metric][0] is not None else math.nan for r in rows]
        spreads = [r[metric][1] or 0.0 for r in rows]
        axis.bar(range(len(rows)), means, yerr=spreads, capsize=4, color="#4c72b0", label="this code")
        axis.scatter(
            range(len(rows)),
            [r[paper_key] for r in rows],
            color="#dd8452",
            marker="D",
            zorder=3,
            label="paper (GPU, 30k / 200k steps)",
        )
        axis.set_xticks(range(len(rows)), names, rotation=20, fontsize=8)
        axis.set_title(title)
        axis.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)


def plot_table1_curves(variants: list[Variant], store: RowStore, exposures: tuple[int, ...], path: Path) -> None:
    """HDR PSNR against training seconds of every Table 1 row, averaged point by point over its runs."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.5, 4))
    for variant in variants:
        curves = [
            store.rows[s.key]["curve"]
            for s in variant.runs(exposures)
            if store.rows.get(s.key, {}).get("status") == "ok"
        ]
        if not curves:
            continue
        length = min(len(c) for c in curves)
        seconds = [statistics.fmean(c[i]["train_seconds"] for c in curves) for i in range(length)]
        hdr = [statistics.fmean(c[i]["hdr_psnr"] for c in curves) for i in range(length)]
        axis.plot(seconds, hdr, marker="o", label=variant.name)
    axis.set_xlabel("training seconds")
    axis.set_ylabel("HDR PSNR (dB)")
    axis.set_title("Table 1 rows: HDR PSNR against training time")
    axis.grid(alpha=0.3)
    axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
