"""The one training loop (any backbone, any method), its hooks, and loading a trained pipeline.

    trainer = build_trainer(config, "gs")        # a Pipeline, Adam, the data, step and seconds
    metrics = trainer.train()                    # progress, periodic eval, checkpoints, metrics.json

`Trainer.fit(hooks)` is the loop itself: it stops at --max-steps or --max-seconds and refuses a
run that keeps producing non-finite losses; everything else (progress bar, evaluation,
checkpoints, the benchmarks' curves) is a `TrainingHook`.
"""

import dataclasses
import json
import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, NamedTuple

import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from mono_hdr_plugin.backbone import Backbone
from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.checkpoints import config_from_dict, config_to_json, load_checkpoint, save_checkpoint
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.evaluation import evaluate
from mono_hdr_plugin.data.layouts import LAYOUTS
from mono_hdr_plugin.methods import METHODS, HdrMethod, MethodConfig, Targets
from mono_hdr_plugin.metrics import psnr
from mono_hdr_plugin.pipeline import Pipeline
from mono_hdr_plugin.registry import get_backbone

console = Console(stderr=True)
# Under --max-seconds: steps before the first estimate of the run length (the first ones pay for
# compilation and caches), estimate again every this many steps, over this many recent steps.
RUN_LENGTH_WARMUP = 5
RUN_LENGTH_EVERY = 25
RUN_LENGTH_WINDOW = 50


@dataclass
class TrainConfig:
    """Train one backbone with one method; the backbone's own options follow."""

    backbone: Any
    data: Annotated[DataConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=DataConfig)
    hdr: Annotated[MethodConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=MethodConfig)
    preset: str | None = None
    """Start from a named preset of the backbone (listed by `mono-hdr backbones`; default: its
    first); other flags override it."""
    max_steps: int = 3000
    """Optimiser steps (the run ends here or at --max-seconds, whichever comes first)."""
    max_seconds: float | None = None
    """Stop after this many seconds of training (evaluation and checkpoints not counted).
    Schedules scale to the steps that fit, estimated from the measured step time."""
    out: Path = Path("outputs/run")
    """Output folder: checkpoints/, renders/, metrics.json."""
    resume: bool = False
    """Continue from OUT/checkpoints/latest.pt."""
    seed: int = 0
    """Seed of initialisation and view order."""
    hdr_view_ratio: str = "1:1"
    """LDR:HDR training-view ratio: 1:1 every view has HDR ground truth, 2:1 half of them, 1:0
    none (LDR only), 0:1 HDR only (no LDR loss)."""
    eval_every: int = 0
    """Evaluate on the test views every N steps (0: only at the end)."""
    checkpoint_every: int = 1000
    """Write OUT/checkpoints/latest.pt every N steps (and at the end)."""
    max_eval_views: int | None = None
    """Evaluate on at most this many test views (None: all)."""
    save_renders: bool = True
    """Write EXR (HDR) and PNG (LDR, tone-mapped HDR) renders of the test views at the end."""
    nan_patience: int = 20
    """Stop after this many consecutive steps with a non-finite loss or gradient."""
    quiet: bool = False
    """No progress bar (tests, benchmarks)."""
    viewer: bool = False
    """Watch training live in the browser (see `mono-hdr view --help`); it stays open after training."""
    viewer_port: int = 7007
    """Port of the --viewer (the next free one when taken)."""
    viewer_host: str = "127.0.0.1"
    """Address the --viewer listens on; anything but localhost opens it to the network."""


class TrainingDiverged(RuntimeError):
    """Too many consecutive steps produced a non-finite loss or gradient."""


def parse_view_ratio(ratio: str) -> tuple[int, int]:
    try:
        ldr, hdr = (int(part) for part in ratio.split(":"))
    except ValueError as error:
        raise ValueError(f"--hdr-view-ratio must look like 2:1 (LDR:HDR), got {ratio!r}") from error
    if ldr < 0 or hdr < 0 or ldr + hdr == 0:
        raise ValueError(f"--hdr-view-ratio needs non-negative parts, not both zero; got {ratio!r}")
    return ldr, hdr


def check_train_config(config: TrainConfig) -> None:
    """Refuse out-of-range run flags before any work is done, naming the flag."""
    minimums = {"max_steps": 0, "checkpoint_every": 1, "eval_every": 0, "nan_patience": 1}
    for name, minimum in minimums.items():
        value = getattr(config, name)
        if value < minimum:
            raise ValueError(f"--{name.replace('_', '-')} must be an integer >= {minimum}, got {value}")
    if config.max_seconds is not None and not (math.isfinite(config.max_seconds) and config.max_seconds > 0):
        raise ValueError(f"--max-seconds must be a positive number of seconds, got {config.max_seconds}")
    if config.max_eval_views is not None and config.max_eval_views < 1:
        raise ValueError(f"--max-eval-views must be >= 1 (or omitted for all views), got {config.max_eval_views}")
    parse_view_ratio(config.hdr_view_ratio)
    METHODS.get(config.hdr.method)  # a misspelt method or layout is named before any data is read
    if config.data.layout != "auto":
        LAYOUTS.get(config.data.layout)


def hdr_supervised_views(num_views: int, ratio: str) -> list[bool]:
    """Which training views keep their HDR ground truth, spread evenly, for an LDR:HDR ratio."""
    ldr, hdr = parse_view_ratio(ratio)
    if hdr == 0:
        return [False] * num_views
    fraction = 1.0 if ldr <= hdr else hdr / ldr
    count = max(1, math.ceil(fraction * num_views))
    chosen = {int(i * num_views / count) for i in range(count)}
    return [i in chosen for i in range(num_views)]


class TrainingHook:
    """Something the training loop calls: at the start, after every good step, at the end."""

    def on_start(self, trainer: "Trainer") -> None:
        pass

    def after_step(self, trainer: "Trainer", record: dict[str, Any]) -> None:
        pass

    def on_end(self, trainer: "Trainer") -> None:
        pass


class Trainer:
    """Owns a pipeline (backbone + method), its optimiser and the data for one run."""

    def __init__(self, config: TrainConfig, backbone_name: str, scene: SceneData):
        check_train_config(config)
        self.config, self.scene = config, scene
        torch.manual_seed(config.seed)
        ldr_share, _ = parse_view_ratio(config.hdr_view_ratio)
        method_config = config.hdr
        if ldr_share == 0:  # HDR-only row of the ratio study: no LDR photo is used
            method_config = MethodConfig(**{**vars(method_config), "use_ldr_loss": False, "use_h2l_loss": False})
        self.pipeline = Pipeline.create(backbone_name, config.backbone, method_config, scene.scene_info())
        self.run_length = config.max_steps
        self.pipeline.set_run_length(self.run_length)
        self.hdr_views = hdr_supervised_views(len(scene.train), config.hdr_view_ratio)
        groups = self.pipeline.parameter_groups()
        for group in groups:
            group["base_lr"] = group["lr"]
        self.optimizer = torch.optim.Adam(groups, eps=1e-15, fused=True)  # one kernel per group, no per-tensor loop
        self.generator = torch.Generator().manual_seed(config.seed)
        self.view_order: list[int] = []
        self.step = 0
        self.train_seconds = 0.0
        self.recent_step_seconds: deque[float] = deque(maxlen=RUN_LENGTH_WINDOW)
        self.history: list[dict] = []

    @property
    def backbone(self) -> Backbone:
        return self.pipeline.backbone

    @property
    def method(self) -> HdrMethod:
        return self.pipeline.method

    @property
    def backbone_name(self) -> str:
        return self.pipeline.backbone_name

    @property
    def finished(self) -> bool:
        """--max-steps reached, or --max-seconds of training spent."""
        budget = self.config.max_seconds
        return self.step >= self.config.max_steps or (budget is not None and self.train_seconds >= budget)

    def _update_run_length(self) -> None:
        """Under --max-seconds, re-estimate the steps that fit from the recent step time and tell
        the backbone when the estimate moved, so its schedules end with the budget."""
        budget = self.config.max_seconds
        if budget is None or self.step < RUN_LENGTH_WARMUP or self.step % RUN_LENGTH_EVERY not in (0, RUN_LENGTH_WARMUP):
            return
        per_step = sum(self.recent_step_seconds) / len(self.recent_step_seconds)
        remaining = max(budget - self.train_seconds, 0.0)
        estimate = min(self.config.max_steps, self.step + max(1, int(remaining / per_step)))
        if abs(estimate - self.run_length) > 0.02 * self.run_length:
            self.run_length = estimate
            self.pipeline.set_run_length(estimate)

    # ----------------------------------------------------------------- training
    def _next_view(self) -> int:
        if not self.view_order:  # a fresh random permutation each epoch, as 3DGS does
            self.view_order = torch.randperm(len(self.scene.train), generator=self.generator).tolist()
        return self.view_order.pop()

    def _batch(self, view: View, use_hdr: bool) -> tuple[Camera, Targets]:
        hdr = view.hdr if use_hdr else None
        batch_size = self.backbone.pixel_batch
        if batch_size is None:
            return view.camera, Targets(ldr=view.image, exposure=view.exposure, hdr=hdr)
        height, width = view.camera.height, view.camera.width
        flat = torch.randint(0, height * width, (batch_size,), generator=self.generator)
        rows, cols = flat // width, flat % width
        pixels = torch.stack([cols.float() + 0.5, rows.float() + 0.5], -1)
        return (view.camera.with_pixels(pixels),
                Targets(ldr=view.image[rows, cols], exposure=view.exposure,
                        hdr=None if hdr is None else hdr[rows, cols]))

    def _bad_tensors(self, loss: torch.Tensor) -> list[str]:
        bad = [] if torch.isfinite(loss) else ["loss"]
        for group in self.optimizer.param_groups:
            for index, param in enumerate(group["params"]):
                if param.grad is not None and not torch.isfinite(param.grad).all():
                    bad.append(f"grad of {group['name']}[{index}] {tuple(param.shape)}")
        return bad

    def train_step(self) -> dict[str, Any]:
        """One optimiser step on one training view; returns the loss terms (floats)."""
        started = time.perf_counter()
        index = self._next_view()
        view = self.scene.train[index]
        camera, targets = self._batch(view, self.hdr_views[index])
        for group in self.optimizer.param_groups:
            group["lr"] = self.pipeline.learning_rate(group, self.step)
        features, output = self.pipeline(camera, targets.exposure)
        terms = self.pipeline.losses(output, targets, self.step)
        loss = torch.stack(list(terms.values())).sum()
        loss.backward()
        bad = self._bad_tensors(loss)
        if bad:
            self.optimizer.zero_grad(set_to_none=True)
        else:
            self.optimizer.step()
            self.pipeline.after_step(self.step, features, self.optimizer)
            self.optimizer.zero_grad(set_to_none=True)
        self.step += 1
        elapsed = time.perf_counter() - started
        self.train_seconds += elapsed
        self.recent_step_seconds.append(elapsed)
        self._update_run_length()
        record = {name: value.item() for name, value in terms.items()}
        record["loss"] = loss.item()
        record["ldr_psnr"] = psnr(output.ldr.detach().clamp(0, 1), targets.ldr)
        record["skipped"] = bool(bad)
        record["bad_tensors"] = bad
        return record

    def fit(self, hooks: list[TrainingHook] = ()) -> None:
        """Train until --max-steps or --max-seconds, calling `hooks` after every good step.

        A step with a non-finite loss or gradient is skipped; --nan-patience of them in a row
        raise TrainingDiverged.
        """
        failures = 0
        for hook in hooks:
            hook.on_start(self)
        try:
            while not self.finished:
                record = self.train_step()
                if record["skipped"]:
                    failures += 1
                    console.print(f"[yellow]step {self.step}: non-finite {', '.join(record['bad_tensors'])}; "
                                  "step skipped")
                    if failures >= self.config.nan_patience:
                        raise TrainingDiverged(
                            f"{failures} consecutive steps had a non-finite loss or gradient (last: "
                            f"{', '.join(record['bad_tensors'])}); stopped at step {self.step}. The last good "
                            f"checkpoint is {self.checkpoint_path()}: lower the learning "
                            "rates or check the data for NaN/Inf")
                    continue
                failures = 0
                for hook in hooks:
                    hook.after_step(self, record)
        finally:
            for hook in hooks:
                hook.on_end(self)

    def train(self, extra_hooks: list[TrainingHook] = ()) -> dict[str, Any]:
        """The command line's run: progress, periodic eval and checkpoints (and `extra_hooks`: the
        viewer's); then save, evaluate and write OUT/metrics.json (and renders)."""
        config = self.config
        hooks: list[TrainingHook] = [ProgressBar()] if not config.quiet else []
        if config.eval_every:
            hooks.append(EvaluateEvery(config.eval_every))
        hooks.append(CheckpointEvery(config.checkpoint_every))
        self.fit([*hooks, *extra_hooks])
        self.save()
        metrics = self.evaluate(save_renders=config.save_renders)
        write_json(config.out / "metrics.json", metrics)
        return metrics

    # --------------------------------------------------------------- evaluation
    def evaluate(self, save_renders: bool = False) -> dict[str, Any]:
        """Test-view metrics of the current model (eval mode), with the step and training seconds."""
        metrics = evaluate(self.pipeline, self.scene, self.config.max_eval_views,
                           render_dir=self.config.out / "renders" if save_renders else None)
        return {**metrics, "preset": self.config.preset, "steps": self.step, "train_seconds": self.train_seconds}

    # -------------------------------------------------------------- checkpoints
    def checkpoint_path(self) -> Path:
        return self.config.out / "checkpoints" / "latest.pt"

    def save(self) -> None:
        save_checkpoint(self.checkpoint_path(), {
            "backbone_name": self.backbone_name,
            "config": config_to_json(self.config),
            "pipeline": self.pipeline.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "step": self.step,
            "train_seconds": self.train_seconds,
            "run_length": self.run_length,
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "view_order": torch.tensor(self.view_order, dtype=torch.long),
        })

    def restore(self, payload: dict[str, Any]) -> None:
        """Load model, converters, optimiser and RNG state from a checkpoint payload."""
        if payload["backbone_name"] != self.backbone_name:
            raise ValueError(f"the checkpoint holds a {payload['backbone_name']!r} model, not {self.backbone_name!r}")
        self.pipeline.load_state_dict(payload["pipeline"])
        for group, fresh in zip(self.optimizer.param_groups, self.pipeline.parameter_groups(), strict=True):
            group["params"] = list(fresh["params"])  # the (possibly resized) parameters, before Adam's state
        self.optimizer.load_state_dict(payload["optimizer"])
        self.step = payload["step"]
        self.train_seconds = payload["train_seconds"]
        if self.config.max_seconds is not None:  # keep the schedule the time budget had scaled to
            self.run_length = min(payload["run_length"], self.config.max_steps)
            self.pipeline.set_run_length(self.run_length)
        self.generator.set_state(payload["generator"])
        torch.set_rng_state(payload["torch_rng"])
        self.view_order = payload["view_order"].tolist()


class ProgressBar(TrainingHook):
    """A rich progress bar with the loss and the training-view LDR PSNR."""

    def on_start(self, trainer: Trainer) -> None:
        self.progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("loss {task.fields[loss]:.4f}  LDR PSNR {task.fields[psnr]:.2f}"),
                                 TimeElapsedColumn(), console=console)
        self.task = self.progress.add_task(f"{trainer.backbone_name}/{trainer.pipeline.method_name}",
                                           total=trainer.run_length, completed=trainer.step, loss=math.nan,
                                           psnr=math.nan)
        self.progress.start()

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        self.progress.update(self.task, completed=trainer.step, total=trainer.run_length, loss=record["loss"],
                             psnr=record["ldr_psnr"])

    def on_end(self, trainer: Trainer) -> None:
        self.progress.stop()


class EvaluateEvery(TrainingHook):
    """Test-view metrics every `steps` steps (not at the last one: the run evaluates at its end)."""

    def __init__(self, steps: int):
        self.steps = steps

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        if trainer.step % self.steps == 0 and not trainer.finished:
            metrics = trainer.evaluate()
            trainer.history.append(metrics)
            console.print(f"step {trainer.step}: HDR PSNR {metrics.get('hdr_psnr') or math.nan:.2f} dB, "
                          f"LDR PSNR {metrics['ldr_psnr']:.2f} dB")


class CheckpointEvery(TrainingHook):
    """OUT/checkpoints/latest.pt every `steps` steps."""

    def __init__(self, steps: int):
        self.steps = steps

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        if trainer.step % self.steps == 0:
            trainer.save()


def build_trainer(config: TrainConfig, backbone_name: str, scene: SceneData | None = None) -> Trainer:
    """Load the scene (unless given) and set up a Trainer, resuming when asked."""
    check_train_config(config)
    if scene is None:
        from mono_hdr_plugin.data.loading import load_scene  # noqa: PLC0415

        scene = load_scene(config.data)
    trainer = Trainer(config, backbone_name, scene)
    if config.resume:
        trainer.restore(load_checkpoint(trainer.checkpoint_path()))
        console.print(f"resumed from {trainer.checkpoint_path()} at step {trainer.step}")
    return trainer


class TrainedRun(NamedTuple):
    """A pipeline loaded from a checkpoint for evaluation or rendering (no optimiser)."""

    pipeline: Pipeline
    scene: SceneData
    config: TrainConfig
    payload: dict[str, Any]


def load_pipeline(checkpoint: Path, scene: SceneData | None = None, data_path: Path | None = None,
                  scene_name: str | None = None) -> TrainedRun:
    """The trained pipeline of a checkpoint file, with its own data unless other data is given
    (an in-memory `scene`, a dataset folder or a built-in scene name)."""
    payload = load_checkpoint(checkpoint)
    backbone_class = get_backbone(payload["backbone_name"])
    config = config_from_dict(train_config_for(backbone_class.config_class), json.loads(payload["config"]))
    if data_path is not None or scene_name is not None:
        config.data = dataclasses.replace(config.data, data=data_path, scene=scene_name)
    if scene is None:
        from mono_hdr_plugin.data.loading import load_scene  # noqa: PLC0415

        scene = load_scene(config.data)
    pipeline = Pipeline.create(payload["backbone_name"], config.backbone, config.hdr, scene.scene_info())
    pipeline.set_run_length(payload["run_length"])
    pipeline.load_state_dict(payload["pipeline"])
    pipeline.eval()
    return TrainedRun(pipeline, scene, config, payload)


_TRAIN_CONFIGS: dict[type, type] = {}


def train_config_for(backbone_config_class: type) -> type:
    """A TrainConfig subclass whose `backbone` field has the backbone's own config type."""
    if backbone_config_class not in _TRAIN_CONFIGS:
        _TRAIN_CONFIGS[backbone_config_class] = dataclass(type(
            f"Train{backbone_config_class.__name__}", (TrainConfig,), {
                "__annotations__": {"backbone": backbone_config_class},
                "backbone": field(default_factory=backbone_config_class),
                "__doc__": TrainConfig.__doc__,
            }))
    return _TRAIN_CONFIGS[backbone_config_class]
