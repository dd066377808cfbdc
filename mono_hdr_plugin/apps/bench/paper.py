"""`mono-hdr bench paper`: the paper's tables on the built-in scenes, at a training-time budget per
run, over seeds and exposures, next to the paper's figures; and the fair-recipe question.

Every row is a (variant, scene, exposure, seed) run of `runs.run_row`. The variants and the
paper's figures are in `paper_tables`; how the rows are averaged and orderings judged, and the
report, in `paper_report`. This module runs them: the configuration, the grid and the recipe tuning.
"""

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import tyro

from mono_hdr_plugin.apps.bench.paper_report import write_paper_report
from mono_hdr_plugin.apps.bench.paper_tables import (
    LOSS_ROWS,
    PAPER_BASELINE,
    PAPER_CONVERTERS,
    PAPER_RATIOS,
    PAPER_TABLE1,
    PAPER_TABLE1_LDR,
    Variant,
)
from mono_hdr_plugin.apps.bench.report import report_on_exit
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
from mono_hdr_plugin.data.config import TRAINING_RESOLUTION

# The fair-recipe table tunes these method settings for every method alike, times the backbone's
# own `tuning_space()`: every method gets the same number of trials.
METHOD_TUNING_SPACE = {"hdr.converter_lr": (5e-4, 2e-3)}
TableName = Literal["table1", "converters", "losses", "ratios", "recipes"]


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
    resolution: int | None = None
    """Studio scene size, N x N pixels (default: the scenes' own 128; the paper's data is 400 x 400; a size
    not yet rendered is rendered first, once, cached)."""
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
        "resolution": TRAINING_RESOLUTION,
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
            resolution=self.resolution,
            executor=self.executor,
        )


def table_variants(config: BenchPaperConfig) -> list[Variant]:
    """Every variant of the fixed tables (not the tuned recipes), on the backbones reproducing the paper's."""
    backbones, presets = paper_backbones(), parse_presets(config.presets)
    ablation_scenes = config.ablation_scenes or config.scenes

    def spec(row: str, method: str, **options) -> RunSpec:
        return RunSpec(
            backbones[row], method, preset=presets.get(backbones[row]), resolution=config.resolution, **options
        )

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
                    resolution=config.resolution,
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
