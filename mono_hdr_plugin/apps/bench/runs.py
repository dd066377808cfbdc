"""One benchmark run (a "row"), how it is trained and measured, and the executors that run many.

A row is a `RunSpec` (backbone, preset, method, scene, exposure, seed, ablation switches,
tuned overrides) trained under a `RunBudget` (seconds and/or steps) by the one training loop,
with evaluations spread along it (the curve). `run_row` is a plain function of picklable
arguments, so the sequential executor and the Ray executor run exactly the same code, and a
finished row is stored at once: an interrupted sweep resumes from its finished rows.
"""

import dataclasses
import functools
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch
from rich.console import Console
from rich.progress import Progress

from mono_hdr_plugin.core.registry import BACKBONES, get_backbone
from mono_hdr_plugin.core.validation import NON_NEGATIVE, POSITIVE, FlagError, at_least, check_flags, one_of
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.methods.base import MethodConfig
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.hooks import TrainingHook
from mono_hdr_plugin.training.trainer import Trainer

console = Console()
CURVE_KEYS = (
    "steps",
    "train_seconds",
    "hdr_psnr",
    "hdr_ssim",
    "hdr_psnr_gt_max",
    "hdr_ssim_gt_max",
    "hdr_psnr_masked",
    "hdr_psnr_aligned",
    "hdr_median_ratio",
    "hdr_peak_ratio",
    "hdr_peak_ratio_worst",
    "ldr_peak_ratio",
    "chroma_outliers",
    "radiance_scale",
    "ldr_psnr",
    "ldr_ssim",
    "ldr_psnr_per_exposure",
)


@dataclass(frozen=True)
class RunSpec:
    """What one benchmark row trains."""

    backbone: str
    method: str = "mono"
    preset: str | None = None
    """None: the backbone's default preset."""
    scene: str = "demo"
    exposure_index: int = 1
    hdr_view_ratio: str = "1:1"
    losses: tuple[bool, bool, bool] = (True, True, True)
    """L_ldr, L_hdr, L_h2l switches."""
    seed: int = 0
    overrides: tuple[tuple[str, Any], ...] = ()
    """(dotted config path, value) pairs applied on top of the preset: "backbone.lr_sh_dc", "hdr.converter_lr"."""
    resolution: int | None = None
    """Studio scene size, N x N pixels (None: the scene's own 128)."""

    @property
    def key(self) -> str:
        """The row's identity; a row at the scene's own size keeps the key it had before sizes existed."""
        *fields, resolution = dataclasses.astuple(self)
        return "|".join(str(v) for v in fields) + ("" if resolution is None else f"|{resolution}px")


@dataclass(frozen=True)
class RunBudget:
    """How long a row trains and how it is measured along the way."""

    seconds: float | None = None
    """Training seconds (evaluation not counted); None: --steps only."""
    steps: int | None = None
    """Optimiser steps; None: --seconds only. With both, whichever ends first."""
    eval_points: int = 1
    """Evaluations spread evenly along the run (in seconds when timed, else in steps); the last is the result."""
    max_eval_views: int | None = None

    flag_rules: ClassVar = {
        "seconds": POSITIVE,
        "steps": at_least(1),
        "eval_points": at_least(1),
        "max_eval_views": at_least(1),
    }

    def __post_init__(self):
        if self.seconds is None and self.steps is None:
            raise FlagError("a benchmark run needs --budget-seconds or --steps")
        check_flags(self)  # a budget built by a script, not a command's checked config


def paper_backbones() -> dict[str, str]:
    """The paper's backbone rows ("NeRF", "3DGS") -> the first registered backbone reproducing each."""
    found: dict[str, str] = {}
    for name, entry in BACKBONES.available().items():
        if entry.plugin.paper_backbone is not None:
            found.setdefault(entry.plugin.paper_backbone, name)
    return found


def parse_presets(pairs: tuple[str, ...]) -> dict[str, str]:
    """("nerf=paper", ...) -> {"nerf": "paper"}, each checked against the backbone's presets."""
    presets = {}
    for pair in pairs:
        backbone, _, preset = pair.partition("=")
        if preset not in get_backbone(backbone).presets():
            raise FlagError(
                f"--presets {pair!r}: backbone {backbone!r} has no preset {preset!r}; choose one of "
                f"{', '.join(get_backbone(backbone).presets())}"
            )
        presets[backbone] = preset
    return presets


def run_facts() -> dict[str, Any]:
    """Git commit, machine and library versions, stored with every result file."""
    import numpy

    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=Path(__file__).parent
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {
        "git_commit": commit,
        "machine": platform.machine(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }


def reset_peak_memory() -> bool:
    """Start a new peak-memory window at what this process holds now (Linux: the kernel's high-water mark,
    reset through /proc/self/clear_refs), so that rows sharing a process each report their own peak.
    False where the kernel does not allow it: peak_memory_mib is then the process's peak so far."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def peak_memory_mib() -> float:
    """Peak resident memory (MiB) since the last reset_peak_memory, else since the process started."""
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / (1024.0**2 if sys.platform == "darwin" else 1024.0)
    kilobytes = next(int(line.split()[1]) for line in status.splitlines() if line.startswith("VmHWM:"))
    return kilobytes / 1024.0


@functools.lru_cache(maxsize=8)
def cached_scene(name: str, exposure_index: int, resolution: int | None = None) -> SceneData:
    """Scenes loaded once per process for all the rows that use them."""
    from mono_hdr_plugin.data.loading import load_scene

    return load_scene(DataConfig(scene=name, exposure_index=exposure_index, resolution=resolution))


def parse_override(text: str) -> tuple[str, Any]:
    """'dotted.path=VALUE' -> (path, value): VALUE read as JSON (3, 0.5, true, [1, 2], "x"), else
    kept as the bare string (softplus), as the benchmark scripts' --set / --variant take it."""
    path, equals, value = text.partition("=")
    if not (path and equals):
        raise ValueError(f"override {text!r}: expected PATH=VALUE, e.g. backbone.field.l2h_input=raw")
    try:
        return path, json.loads(value)
    except json.JSONDecodeError:
        return path, value


def set_override(config: Any, path: str, value: Any) -> None:
    """config.<path> = value for a dotted path into nested dataclasses, refusing unknown names."""
    *parents, name = path.split(".")
    target = config
    for depth, part in enumerate([*parents, name]):
        names = [f.name for f in dataclasses.fields(target)] if dataclasses.is_dataclass(target) else []
        if part not in names:
            raise ValueError(
                f"override {path!r}: {type(target).__name__} has no field {part!r}"
                + (f" (its fields: {', '.join(names)})" if names else "")
            )
        if depth < len(parents):
            target = getattr(target, part)
    setattr(target, name, value)


def build_run(spec: RunSpec, scene: SceneData, out: Path, budget: RunBudget) -> Trainer:
    """The trainer of one row: the backbone's preset, the row's method, losses, seed and overrides."""
    backbone_class = get_backbone(spec.backbone)
    presets = backbone_class.presets()
    use_ldr, use_hdr, use_h2l = spec.losses
    config = train_config_for(backbone_class.config_class)(
        backbone=dataclasses.replace(presets[spec.preset or next(iter(presets))]),
        preset=spec.preset,
        max_steps=budget.steps or 10**9,
        max_seconds=budget.seconds,
        out=out,
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
        max_eval_views=budget.max_eval_views,
        hdr_view_ratio=spec.hdr_view_ratio,
        seed=spec.seed,
        data=DataConfig(scene=spec.scene, exposure_index=spec.exposure_index, resolution=spec.resolution),
        hdr=MethodConfig(method=spec.method, use_ldr_loss=use_ldr, use_hdr_loss=use_hdr, use_h2l_loss=use_h2l),
    )
    for path, value in spec.overrides:
        set_override(config, path, value)
    return Trainer(config, spec.backbone, scene)


class EvaluateAlong(TrainingHook):
    """Evaluate at evenly spaced points of the run: training seconds under a time budget, else steps."""

    def __init__(self, points: int):
        self.points = points
        self.curve: list[dict[str, Any]] = []

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        fraction = (len(self.curve) + 1) / self.points
        budget = trainer.config.max_seconds
        due = (
            trainer.train_seconds >= budget * fraction
            if budget is not None
            else trainer.step >= trainer.run_length * fraction
        )
        if due or trainer.finished:
            metrics = trainer.evaluate()
            self.curve.append({key: metrics.get(key) for key in CURVE_KEYS})


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

    times: dict[str, list[float]] = {"ldr": [], "ldr_hdr": []}
    with pipeline.evaluating():
        for _ in range(repeats):  # interleaved, so machine load hits both alike
            for name, function in (("ldr", ldr_only), ("ldr_hdr", ldr_hdr)):
                started = time.perf_counter()
                function()
                times[name].append(time.perf_counter() - started)
    return 1.0 / statistics.median(times["ldr"]), 1.0 / statistics.median(times["ldr_hdr"])


def run_row(spec: RunSpec, budget: RunBudget, out: str, threads: int | None = None) -> dict[str, Any]:
    """Train one row to its budget and measure it: the curve, the final metrics, step time, render speed.

    `threads` sets torch's threads (a Ray task gets the CPUs it asked for). Raises what training
    raises (TrainingDiverged included): the executor records the failure.
    """
    caller_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        scene = cached_scene(spec.scene, spec.exposure_index, spec.resolution)
        reset_peak_memory()  # an earlier row in this process (the sequential executor) does not count
        trainer = build_run(spec, scene, Path(out), budget)
        curve = EvaluateAlong(budget.eval_points)
        trainer.fit([curve])
        fps_ldr, fps_ldr_hdr = render_fps(trainer)
        return {
            "key": spec.key,
            "spec": dataclasses.asdict(spec),
            "status": "ok",
            "curve": curve.curve,
            "final": curve.curve[-1],
            "mean_step_seconds": trainer.train_seconds / max(trainer.step, 1),
            "fps_ldr": fps_ldr,
            "fps_ldr_hdr": fps_ldr_hdr,
            "backbone_statistics": trainer.backbone.statistics(),
            "peak_memory_mib": peak_memory_mib(),
            "threads": torch.get_num_threads(),
        }
    finally:  # the sequential executor runs rows in the caller's process: leave its threads as they were
        torch.set_num_threads(caller_threads)


def failed_row(spec: RunSpec, error: BaseException | str, attempts: int) -> dict[str, Any]:
    """The record of a row that kept failing: never dropped, its error kept."""
    message = error if isinstance(error, str) else "".join(traceback.format_exception_only(error)).strip()
    return {
        "key": spec.key,
        "spec": dataclasses.asdict(spec),
        "status": "failed",
        "error": message,
        "attempts": attempts,
    }


@dataclass
class RowStore:
    """Finished rows of one benchmark in OUT/<name>.json, written after every row (atomically).

    Rows of an earlier run with the same settings (budget, ...) are kept, whatever rows it ran: a
    finished row is not run again (resume) and new rows go beside it (a second scene); failed rows
    are run again. The file of an earlier run with other settings is moved aside, never overwritten.
    """

    path: Path
    settings: dict[str, Any]
    facts: dict[str, Any] = field(default_factory=run_facts)
    rows: dict[str, dict] = field(default_factory=dict)

    def __post_init__(self):
        if not self.path.is_file():
            return
        earlier = json.loads(self.path.read_text())
        earlier_settings = earlier.get("settings", {})
        # only this store's keys: files of older versions carry more (the list of rows they ran)
        if all(earlier_settings.get(key) == value for key, value in self.settings.items()):
            self.rows = {key: row for key, row in earlier.get("rows", {}).items() if row.get("status") == "ok"}
            if self.rows:
                console.print(f"resuming: {len(self.rows)} finished rows in {self.path} are kept")
        else:
            aside = self.path.with_suffix(f".earlier-{time.strftime('%Y%m%d-%H%M%S')}.json")
            self.path.rename(aside)
            console.print(f"{self.path} held rows of other settings; moved to {aside}")

    def done(self, spec: RunSpec) -> bool:
        return spec.key in self.rows

    def add(self, row: dict[str, Any]) -> None:
        self.rows[row["key"]] = row
        write_json(self.path, {"facts": self.facts, "settings": self.settings, "rows": self.rows})


@dataclass(frozen=True)
class ExecutorConfig:
    """Where benchmark rows run."""

    executor: str = "sequential"
    """sequential (this process, one row after another) or ray (each row a Ray task; local cluster
    by default, an existing one with --address). Ray: `pip install -e '.[distributed]'`."""
    address: str | None = None
    """Ray cluster address: auto (the cluster `ray start` made on this machine) or HOST:PORT."""
    cpus_per_run: int | None = None
    """CPUs (and torch threads) per row; default: all of this machine's for sequential, 1 for ray."""
    retries: int = 1
    """A row that raises is tried again this many times, then recorded as failed with its error."""

    flag_rules: ClassVar = {
        "executor": one_of("sequential", "ray"),
        "cpus_per_run": at_least(1),
        "retries": NON_NEGATIVE,
    }


def execute(
    specs: list[RunSpec],
    budget: RunBudget,
    store: RowStore,
    runs_dir: Path,
    executor: ExecutorConfig,
    on_row: Callable[[dict], None] = lambda row: None,
) -> None:
    """Run every spec not finished in `store`, recording each row (or its failure) as it ends."""
    check_flags(executor)  # an executor built by a script, not a command's checked config
    pending = [spec for spec in specs if not store.done(spec)]
    run = _run_sequential if executor.executor == "sequential" else _run_ray
    run(pending, budget, store, runs_dir, executor, on_row)


def _run_sequential(specs, budget, store, runs_dir, executor, on_row) -> None:
    with Progress(console=console) as progress:
        task = progress.add_task("benchmark rows", total=len(specs))
        for spec in specs:
            progress.update(
                task,
                description=f"{spec.backbone}/{spec.method} {spec.scene} t{2 * spec.exposure_index + 1} "
                f"seed {spec.seed}",
            )
            row = _run_with_retries(spec, budget, runs_dir, executor)
            store.add(row)
            on_row(row)
            progress.advance(task)


def _run_with_retries(spec: RunSpec, budget: RunBudget, runs_dir: Path, executor: ExecutorConfig) -> dict[str, Any]:
    """`spec`'s row, tried up to 1 + `executor.retries` times; its failure's record when the last attempt fails."""
    attempt = 1
    while True:
        try:
            return run_row(spec, budget, str(runs_dir), executor.cpus_per_run)
        except Exception as error:  # noqa: BLE001 - any failure of a run is recorded, never silently dropped
            console.print(f"[yellow]{spec.key}: attempt {attempt} failed: {error}")
            if attempt > executor.retries:
                return failed_row(spec, error, attempt)
        attempt += 1


def _run_ray(specs, budget, store, runs_dir, executor, on_row) -> None:
    try:
        import ray
    except ImportError as error:
        raise ValueError("--executor ray needs Ray: pip install -e '.[distributed]' (or pip install ray)") from error
    cpus = executor.cpus_per_run or 1
    ray.init(
        address=executor.address,
        ignore_reinit_error=True,
        log_to_driver=False,
        runtime_env={"env_vars": {"OMP_NUM_THREADS": str(cpus)}},
    )
    remote = ray.remote(run_row).options(num_cpus=cpus, max_retries=executor.retries, retry_exceptions=True)
    futures = {remote.remote(spec, budget, str(runs_dir), cpus): spec for spec in specs}
    with Progress(console=console) as progress:
        task = progress.add_task(f"benchmark rows on Ray ({cpus} CPU each)", total=len(specs))
        while futures:
            ready, _ = ray.wait(list(futures), num_returns=1)
            spec = futures.pop(ready[0])
            try:
                row = ray.get(ready[0])
            except Exception as error:  # noqa: BLE001 - the task raised on every attempt, or its worker died
                row = failed_row(spec, _ray_cause(error), executor.retries + 1)
            store.add(row)
            on_row(row)
            progress.advance(task)


def _ray_cause(error: BaseException) -> str:
    """The user's exception inside Ray's wrapper, in one line."""
    cause = getattr(error, "cause", None) or error
    return "".join(traceback.format_exception_only(cause)).strip().splitlines()[-1]
