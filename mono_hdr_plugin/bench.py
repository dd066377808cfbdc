"""What accuracy costs in time: `mono-hdr bench curves`, `bench paper`, `bench raster`.

Every figure is measured in the run that reports it; results are JSON (with git commit,
machine facts and library versions), Markdown tables and matplotlib plots. Finished rows
are written after each run, so an interrupted benchmark keeps them.
"""

import contextlib
import math
import os
import platform
import resource
import statistics
import subprocess
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal

import torch
from rich.console import Console
from rich.progress import Progress
from rich.table import Table

from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.methods import MethodConfig
from mono_hdr_plugin.registry import BACKBONES, get_backbone
from mono_hdr_plugin.train import Trainer, TrainingHook, train_config_for

console = Console()

# The paper's figures (docs/method.md), HDR PSNR in dB, by the paper's backbone rows; a registered
# backbone reproduces a row through its `paper_backbone`. The ablations are the paper's 3DGS ones.
PAPER_BASELINE = {"NeRF": "hdr-nerf", "3DGS": "hdr-gs"}
PAPER_TABLE1 = {("NeRF", "hdr-nerf"): 13.76, ("NeRF", "mono"): 32.86, ("3DGS", "hdr-gs"): 35.30,
                ("3DGS", "mono"): 38.57}
PAPER_CONVERTERS = {"mlp-l2h": 19.02, "mlp-h2l": 38.43, "no-h2l": 38.19, "mono": 38.57}
LOSS_ROWS = {  # name -> (L_ldr, L_hdr, L_h2l), paper figure (None: "fails to train", no figure)
    "ldr": ((True, False, False), None), "hdr": ((False, True, False), 33.93),
    "h2l": ((False, False, True), 11.87), "ldr+hdr": ((True, True, False), 38.19),
    "ldr+h2l": ((True, False, True), 13.50), "hdr+h2l": ((False, True, True), 33.58),
    "ldr+hdr+h2l": ((True, True, True), 38.57),
}
PAPER_RATIOS = {"mono": {"1:1": 38.57, "2:1": 37.97, "3:1": 37.53, "5:1": 35.51, "0:1": 33.93, "1:0": 13.50},
                "hdr-gs": {"1:1": 35.30, "2:1": 35.26, "3:1": 35.16, "5:1": 34.89, "0:1": 33.46, "1:0": 10.51}}


def paper_backbones() -> dict[str, str]:
    """The paper's backbone rows ("NeRF", "3DGS") -> the first registered backbone reproducing each."""
    found: dict[str, str] = {}
    for name, entry in BACKBONES.available().items():
        if entry.plugin.paper_backbone is not None:
            found.setdefault(entry.plugin.paper_backbone, name)
    return found


def run_facts() -> dict[str, Any]:
    """Git commit, machine and library versions, stored with every result file."""
    import numpy  # noqa: PLC0415

    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True,
                                cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {"git_commit": commit, "machine": platform.machine(), "processor": platform.processor(),
            "cpu_count": os.cpu_count(), "torch_threads": torch.get_num_threads(), "python": platform.python_version(),
            "torch": torch.__version__, "numpy": numpy.__version__, "date": time.strftime("%Y-%m-%d %H:%M:%S")}


def peak_memory_mib() -> float:
    """Peak resident memory of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@torch.no_grad()
def render_fps(trainer: Trainer, repeats: int = 3) -> tuple[float, float]:
    """Frames per second of one test view: LDR only (3 channels) and LDR + HDR (the method)."""

    view = trainer.scene.test[0]
    camera, pipeline = view.camera, trainer.pipeline

    def ldr_only():
        for part in pipeline.camera_chunks(camera):
            features = pipeline.backbone.render_ldr_features(part)
            features.composite(features.colors)

    def ldr_hdr():
        pipeline.render(camera, view.exposure)

    times = {"ldr": [], "ldr_hdr": []}
    for _ in range(repeats):  # interleaved, so machine load hits both alike
        for name, function in (("ldr", ldr_only), ("ldr_hdr", ldr_hdr)):
            started = time.perf_counter()
            function()
            times[name].append(time.perf_counter() - started)
    return 1.0 / statistics.median(times["ldr"]), 1.0 / statistics.median(times["ldr_hdr"])


@dataclass
class RunSpec:
    """One training run of a benchmark."""

    backbone: str
    method: str = "mono"
    preset: str | None = None
    scene: str = "demo"
    exposure_index: int = 1
    hdr_view_ratio: str = "1:1"
    losses: tuple[bool, bool, bool] = (True, True, True)

    @property
    def key(self) -> str:
        return "|".join(str(v) for v in (self.backbone, self.method, self.preset, self.scene, self.exposure_index,
                                         self.hdr_view_ratio, self.losses))


def build_run(spec: RunSpec, scene: SceneData, out: Path, max_eval_views: int | None, max_steps: int = 10**9,
              max_seconds: float | None = None) -> Trainer:
    """The trainer of one benchmark row: the backbone's preset, the row's method and losses."""
    backbone_class = get_backbone(spec.backbone)
    config_class = backbone_class.config_class
    presets = backbone_class.presets()
    backbone_config = presets[spec.preset or next(iter(presets))]
    use_ldr, use_hdr, use_h2l = spec.losses
    config = train_config_for(config_class)(
        backbone=backbone_config, preset=spec.preset, max_steps=max_steps, max_seconds=max_seconds, out=out,
        quiet=True, save_renders=False, checkpoint_every=10**9, max_eval_views=max_eval_views,
        hdr_view_ratio=spec.hdr_view_ratio,
        data=DataConfig(scene=spec.scene, exposure_index=spec.exposure_index),
        hdr=MethodConfig(method=spec.method, use_ldr_loss=use_ldr, use_hdr_loss=use_hdr, use_h2l_loss=use_h2l))
    return Trainer(config, spec.backbone, scene)


class SceneCache:
    """Scenes loaded once per (name, exposure index) for a whole benchmark."""

    def __init__(self):
        self._scenes: dict[tuple[str, int], SceneData] = {}

    def get(self, name: str, exposure_index: int) -> SceneData:
        key = (name, exposure_index)
        if key not in self._scenes:
            self._scenes[key] = load_scene(DataConfig(scene=name, exposure_index=exposure_index))
        return self._scenes[key]


CURVE_KEYS = ("steps", "train_seconds", "hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "ldr_psnr", "ldr_ssim",
              "ldr_psnr_per_exposure")


class EvaluateAtSeconds(TrainingHook):
    """Evaluate at evenly spaced training times of a --max-seconds run (evaluation not counted)."""

    def __init__(self, points: int):
        self.points = points
        self.curve: list[dict[str, Any]] = []

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        due = trainer.config.max_seconds * (len(self.curve) + 1) / self.points
        if trainer.train_seconds >= due or trainer.finished:
            metrics = trainer.evaluate()
            self.curve.append({key: metrics[key] for key in CURVE_KEYS})


def train_for(trainer: Trainer, eval_points: int) -> list[dict[str, Any]]:
    """Train a --max-seconds run to its end, evaluating at `eval_points` evenly spaced training times."""
    curve = EvaluateAtSeconds(eval_points)
    trainer.fit([curve])
    return curve.curve


# ------------------------------------------------------------------------------ curves
@dataclass
class BenchCurvesConfig:
    """Quality versus training time for each backbone x method x preset x scene."""

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
    budget_seconds: float | None = None
    """Training seconds per run (default 60 quick, 600 full)."""
    eval_points: int = 5
    """Evaluations along each run."""
    max_eval_views: int | None = None
    """Test views per evaluation (default 4 quick, all full)."""


def bench_curves(config: BenchCurvesConfig) -> dict[str, Any]:
    budget = config.budget_seconds or (60.0 if config.quick else 600.0)
    max_eval_views = config.max_eval_views or (4 if config.quick else None)
    backbones = config.backbones or tuple(paper_backbones().values())
    presets = parse_presets(config.presets)
    specs = [RunSpec(backbone=b, method=m, preset=presets.get(b), scene=s) for s in config.scenes for b in backbones
             for m in config.methods]
    results = {"facts": run_facts(), "budget_seconds": budget, "runs": []}
    scenes = SceneCache()
    with Progress(console=console) as progress, _report_on_exit(lambda: write_curves_report(results, config.out)):
        task = progress.add_task("bench curves", total=len(specs))
        for spec in specs:
            progress.update(task, description=f"{spec.backbone}/{spec.method} on {spec.scene}")
            trainer = build_run(spec, scenes.get(spec.scene, spec.exposure_index), config.out / "runs",
                                max_eval_views, max_seconds=budget)
            curve = train_for(trainer, config.eval_points)
            fps_ldr, fps_ldr_hdr = render_fps(trainer)
            results["runs"].append({"backbone": spec.backbone, "method": spec.method, "preset": spec.preset,
                                    "scene": spec.scene, "curve": curve, "final": curve[-1],
                                    "peak_memory_mib": peak_memory_mib(), "fps_ldr": fps_ldr,
                                    "fps_ldr_hdr": fps_ldr_hdr, "hdr_fps_cost": 1.0 - fps_ldr_hdr / fps_ldr})
            write_json(config.out / "curves.json", results)
            progress.advance(task)
    return results


def parse_presets(pairs: tuple[str, ...]) -> dict[str, str]:
    """("nerf=paper", ...) -> {"nerf": "paper"}, each checked against the backbone's presets."""
    presets = {}
    for pair in pairs:
        backbone, _, preset = pair.partition("=")
        if preset not in get_backbone(backbone).presets():
            raise ValueError(f"--presets {pair!r}: backbone {backbone!r} has no preset {preset!r}; choose one of "
                             f"{', '.join(get_backbone(backbone).presets())}")
        presets[backbone] = preset
    return presets


@contextlib.contextmanager
def _report_on_exit(write_report):
    """Write the Markdown/plots of the finished rows even when the run is interrupted."""
    try:
        yield
    finally:
        write_report()


def _label(run: dict) -> str:
    return f"{run['backbone']}{'-' + run['preset'] if run.get('preset') else ''} / {run['method']}"


def write_curves_report(results: dict, out: Path) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    lines = ["| backbone / method | scene | steps | seconds | HDR PSNR | HDR SSIM | LDR PSNR | LDR SSIM | fps LDR | "
             "fps LDR+HDR | peak MiB |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for run in results["runs"]:
        final = run["final"]
        lines.append(f"| {_label(run)} | {run['scene']} | {final['steps']} | {final['train_seconds']:.0f} | "
                     f"{_fmt(final['hdr_psnr'])} | {_fmt(final['hdr_ssim'], 3)} | {_fmt(final['ldr_psnr'])} | "
                     f"{_fmt(final['ldr_ssim'], 3)} | {run['fps_ldr']:.1f} | {run['fps_ldr_hdr']:.1f} | "
                     f"{run['peak_memory_mib']:.0f} |")
    (out / "curves.md").write_text("\n".join(lines) + "\n")

    figure, axes = plt.subplots(1, 2, figsize=(11, 4))
    for run in results["runs"]:
        seconds = [p["train_seconds"] for p in run["curve"]]
        axes[0].plot(seconds, [p["hdr_psnr"] for p in run["curve"]], marker="o", label=_label(run))
        axes[1].plot(seconds, [p["ldr_psnr"] for p in run["curve"]], marker="o", label=_label(run))
    for axis, title in zip(axes, ("HDR mu-law PSNR (dB)", "LDR PSNR (dB)")):
        axis.set_xlabel("training seconds (2-core CPU)")
        axis.set_title(title)
        axis.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(out / "curves.png", dpi=120)
    plt.close(figure)

    figure, axis = plt.subplots(figsize=(6, 4))
    for run in results["runs"]:
        axis.scatter(run["final"]["train_seconds"], run["final"]["hdr_psnr"], s=40)
        axis.annotate(_label(run), (run["final"]["train_seconds"], run["final"]["hdr_psnr"]), fontsize=7)
    axis.set_xlabel("training seconds")
    axis.set_ylabel("final HDR PSNR (dB)")
    axis.set_title("Pareto: final quality vs training time")
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(out / "pareto.png", dpi=120)
    plt.close(figure)


def _fmt(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


# ------------------------------------------------------------------------------- paper
@dataclass
class BenchPaperConfig:
    """The paper's tables re-run on studio scenes, single-exposure setting, next to its figures."""

    out: Path = Path("benchmarks/results")
    """Folder for paper.json and paper.md."""
    quick: bool = False
    """A size that finishes in minutes on 2 cores."""
    scene: str = "demo"
    """Studio scene."""
    exposure_indices: tuple[int, ...] | None = None
    """Exposures t1/t3/t5 (0, 1, 2) to average over (default: t3 quick, all three full)."""
    steps: int | None = None
    """Training steps per row (default 300 quick, 3000 full)."""
    presets: tuple[str, ...] = ()
    """BACKBONE=PRESET pairs; other backbones run their default preset."""
    max_eval_views: int | None = None
    """Test views per evaluation (default 6 quick, all full)."""
    tables: tuple[Literal["table1", "converters", "losses", "ratios"], ...] = ("table1", "converters", "losses", "ratios")
    """Which tables to run."""


def paper_specs(config: BenchPaperConfig) -> dict[str, list[tuple[str, RunSpec, float | None]]]:
    """table -> [(variant, spec without exposure, paper figure)], on the backbones reproducing the paper's."""
    backbones, presets = paper_backbones(), parse_presets(config.presets)

    def spec(row: str, method: str, **options) -> RunSpec:
        return RunSpec(backbones[row], method, preset=presets.get(backbones[row]), scene=config.scene, **options)

    tables = {"table1": [(m, spec(row, m), PAPER_TABLE1[(row, m)]) for row in PAPER_BASELINE if row in backbones
                         for m in (PAPER_BASELINE[row], "mono")]}
    if "3DGS" in backbones:
        tables |= {
            "converters": [(m, spec("3DGS", m), PAPER_CONVERTERS[m]) for m in PAPER_CONVERTERS],
            "losses": [(name, spec("3DGS", "mono", losses=switches), figure)
                       for name, (switches, figure) in LOSS_ROWS.items()],
            "ratios": [(f"{m} {r}", spec("3DGS", m, hdr_view_ratio=r), PAPER_RATIOS[m][r])
                       for m in ("mono", "hdr-gs") for r in PAPER_RATIOS[m]],
        }
    return {name: rows for name, rows in tables.items() if name in config.tables}


def bench_paper(config: BenchPaperConfig) -> dict[str, Any]:
    exposures = config.exposure_indices or ((1,) if config.quick else (0, 1, 2))
    steps = config.steps or (300 if config.quick else 3000)
    max_eval_views = config.max_eval_views or (6 if config.quick else None)
    tables = paper_specs(config)
    unique = {spec.key: spec for rows in tables.values() for _, spec, _ in rows}
    results: dict[str, Any] = {"facts": run_facts(), "scene": config.scene, "exposure_indices": list(exposures),
                               **{name: [] for name in tables}}
    finished: dict[str, dict] = {}
    scenes = SceneCache()
    with Progress(console=console) as progress, _report_on_exit(lambda: write_paper_report(results, config.out)):
        task = progress.add_task("bench paper", total=len(unique) * len(exposures))
        for key, spec in unique.items():
            per_exposure = []
            for index in exposures:
                progress.update(task, description=f"{spec.backbone}/{spec.method} {spec.hdr_view_ratio} "
                                                  f"losses={spec.losses} t{2 * index + 1}")
                run = replace(spec, exposure_index=index)
                trainer = build_run(run, scenes.get(spec.scene, index), config.out / "runs", max_eval_views,
                                    max_steps=steps)
                trainer.fit()
                per_exposure.append(trainer.evaluate())
                progress.advance(task)
            finished[key] = _average_runs(per_exposure)
            _fill_tables(results, tables, finished)
            write_json(config.out / "paper.json", results)
    return results


def _average_runs(runs: list[dict]) -> dict[str, Any]:
    keys = ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "ldr_psnr", "ldr_ssim", "train_seconds", "steps")
    return {key: _mean_or_none([run[key] for run in runs]) for key in keys}


def _mean_or_none(values: list) -> float | None:
    values = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return sum(values) / len(values) if values else None


def _fill_tables(results: dict, tables: dict, finished: dict) -> None:
    for name, rows in tables.items():
        results[name] = [{"backbone": spec.backbone, "variant": variant, "scene": spec.scene, **finished[spec.key],
                          "paper_hdr_psnr": figure}
                         for variant, spec, figure in rows if spec.key in finished]


def ordering_agreement(rows: list[dict]) -> tuple[int, int, list[str]]:
    """Pairs of rows (with a paper figure) ordered the same way by us and by the paper."""
    rows = [r for r in rows if r["paper_hdr_psnr"] is not None and r["hdr_psnr"] is not None]
    agree, total, disagreements = 0, 0, []
    for i, a in enumerate(rows):
        for b in rows[i + 1:]:
            if a["paper_hdr_psnr"] == b["paper_hdr_psnr"]:
                continue
            total += 1
            if (a["paper_hdr_psnr"] > b["paper_hdr_psnr"]) == (a["hdr_psnr"] > b["hdr_psnr"]):
                agree += 1
            else:
                disagreements.append(f"{a['variant']} vs {b['variant']}")
    return agree, total, disagreements


def write_paper_report(results: dict, out: Path) -> None:
    lines = [f"Scene `{results['scene']}`, single exposure, exposure indices {results['exposure_indices']} "
             f"(averaged); git {results['facts']['git_commit'][:10]}.", ""]
    for name in ("table1", "converters", "losses", "ratios"):
        if name not in results or not results[name]:
            continue
        lines += [f"### {name}", "", "| backbone | variant | HDR PSNR | paper HDR PSNR | HDR SSIM | LDR PSNR | LDR SSIM "
                  "| seconds | steps |", "|---|---|---|---|---|---|---|---|---|"]
        for row in results[name]:
            lines.append(f"| {row['backbone']} | {row['variant']} | {_fmt(row['hdr_psnr'])} | "
                         f"{_fmt(row['paper_hdr_psnr'])} | {_fmt(row['hdr_ssim'], 3)} | {_fmt(row['ldr_psnr'])} | "
                         f"{_fmt(row['ldr_ssim'], 3)} | {_fmt(row['train_seconds'], 0)} | {_fmt(row['steps'], 0)} |")
        agree, total, disagreements = ordering_agreement(results[name])
        lines += ["", f"Orderings that hold: {agree} of {total} pairs agree with the paper"
                  + (f"; not: {', '.join(disagreements)}." if disagreements else "."), ""]
    (out / "paper.md").write_text("\n".join(lines) + "\n")
    console.print("\n".join(lines))


BENCHMARKS = {"curves": (BenchCurvesConfig, bench_curves), "paper": (BenchPaperConfig, bench_paper)}


def all_benchmarks() -> dict[str, tuple[type, Any]]:
    """The benchmarks every pipeline has, plus those each registered backbone contributes
    (`Backbone.benchmarks`, e.g. the 3DGS rasteriser's `raster`)."""
    found = dict(BENCHMARKS)
    for entry in BACKBONES.available().values():
        for name, benchmark in entry.plugin.benchmarks().items():
            if name in found:
                raise ValueError(f"backbone {entry.name!r} contributes a benchmark named {name!r}, which exists "
                                 "already; rename it")
            found[name] = benchmark
    return found
