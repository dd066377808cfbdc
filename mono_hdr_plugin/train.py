"""The one training loop (any backbone, any method), its hooks, and loading a trained pipeline.

    trainer = build_trainer(config, "gs")        # a Pipeline, Adam, the data, step and seconds
    metrics = trainer.train()                    # progress, periodic eval, checkpoints, metrics.json

`Trainer.fit(hooks)` is the loop itself: it stops at --max-steps or --max-seconds and refuses a
run that keeps producing non-finite losses; everything else (progress bar, evaluation,
checkpoints, the benchmarks' curves) is a `TrainingHook`. `run_training` is `mono-hdr train`: it
claims --out first (one run per folder, no earlier run replaced unasked; docs/robustness.md).
"""

import contextlib
import dataclasses
import json
import math
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Callable, ClassVar, NamedTuple

import torch
import tyro
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from mono_hdr_plugin.backbone import Backbone
from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.checkpoints import (CheckpointError, config_from_dict, config_to_json, load_checkpoint,
                                         save_checkpoint)
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.errors import os_error_line
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.evaluation import evaluate
from mono_hdr_plugin.exposure import ExposureConfig, ViewExposures, build_view_exposures
from mono_hdr_plugin.data.layouts import LAYOUTS
from mono_hdr_plugin.methods import METHODS, HdrMethod, MethodConfig, Targets
from mono_hdr_plugin.metrics import psnr
from mono_hdr_plugin.outputs import OutputError, claim_output
from mono_hdr_plugin.pipeline import Pipeline
from mono_hdr_plugin.registry import get_backbone
from mono_hdr_plugin.validation import (NON_NEGATIVE, POSITIVE, SEED, FlagError, at_least, between, check_flags,
                                        iter_flags)

console = Console(stderr=True)
# Under --max-seconds: steps before the first estimate of the run length (the first ones pay for
# compilation and caches), estimate again every this many steps, over this many recent steps.
RUN_LENGTH_WARMUP = 5
RUN_LENGTH_EVERY = 25
RUN_LENGTH_WINDOW = 50
TRAIN_OUTPUTS = ("checkpoints", "renders", "metrics.json", "viewer")
"""What `mono-hdr train` writes in --out; --overwrite removes exactly these."""


@dataclass
class TrainConfig:
    """Train one backbone with one method; the backbone's own options follow."""

    backbone: Any
    data: Annotated[DataConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=DataConfig)
    hdr: Annotated[MethodConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=MethodConfig)
    exposure: Annotated[ExposureConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=ExposureConfig)
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
    """Continue the run in --out from OUT/checkpoints/latest.pt (same data, backbone and method)."""
    overwrite: bool = False
    """Replace the earlier run in --out (its checkpoints/, renders/ and metrics.json) instead of refusing."""
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

    flag_rules: ClassVar = {"max_steps": NON_NEGATIVE, "max_seconds": POSITIVE, "seed": SEED,
                            "eval_every": NON_NEGATIVE, "checkpoint_every": at_least(1),
                            "max_eval_views": at_least(1), "nan_patience": at_least(1),
                            "viewer_port": between(0, 65535)}


class TrainingDiverged(RuntimeError):
    """Too many consecutive steps produced a non-finite loss or gradient, or none was finite."""


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped training after a finished step; `checkpoint` holds that step."""

    def __init__(self, step: int, checkpoint: Path):
        super().__init__(f"interrupted at step {step}; checkpoint saved to {checkpoint}")
        self.step, self.checkpoint = step, checkpoint


class ResumeMismatch(ValueError):
    """--resume with settings that would continue a different model or data than the checkpoint's."""


# Flags of a run that may change when it is resumed (the schedule, the output, logging).
RESUME_FREE_FLAGS = {"--max-steps", "--max-seconds", "--out", "--resume", "--overwrite", "--eval-every",
                     "--checkpoint-every", "--max-eval-views", "--save-renders", "--nan-patience", "--quiet",
                     "--seed", "--preset", "--viewer", "--viewer-port", "--viewer-host"}
# Flags that make a resumed run a different experiment; the data flags count through the data itself.
RESUME_IDENTITY_FLAGS = {"--method", "--hidden"}
DATA_FLAGS = {"--data", "--scene", "--layout", "--protocol", "--exposure-index", "--fixed-exposure", "--downscale",
              "--exposure-seed"}


def parse_view_ratio(ratio: str) -> tuple[int, int]:
    try:
        ldr, hdr = (int(part) for part in ratio.split(":"))
    except ValueError as error:
        raise ValueError(f"--hdr-view-ratio must look like 2:1 (LDR:HDR), got {ratio!r}") from error
    if ldr < 0 or hdr < 0 or ldr + hdr == 0:
        raise ValueError(f"--hdr-view-ratio needs non-negative parts, not both zero; got {ratio!r}")
    return ldr, hdr


def check_train_config(config: TrainConfig) -> None:
    """Refuse flags that cannot work before any work is done, naming the flag: every numeric flag
    (run, data, method and backbone alike) against its rule (validation.py), then the rest."""
    check_flags(config)
    if config.resume and config.overwrite:
        raise FlagError("--resume continues the run in --out and --overwrite replaces it: pass one of them")
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
        self.pipeline = Pipeline.create(backbone_name, config.backbone, method_config, scene.scene_info(),
                                        build_view_exposures(config.exposure, scene))
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
        self.saved_step: int | None = None
        """Step of the checkpoint at checkpoint_path() this run wrote or resumed from (None: none yet)."""

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
        features, output = self.pipeline(camera, targets.exposure, view=index)
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
        failures = taken = good = 0
        for hook in hooks:
            hook.on_start(self)
        try:
            while not self.finished:
                record = self.train_step()
                taken += 1
                if record["skipped"]:
                    failures += 1
                    console.print(f"[yellow]step {self.step}: non-finite {', '.join(record['bad_tensors'])}; "
                                  "step skipped")
                    if failures >= self.config.nan_patience:
                        raise TrainingDiverged(
                            f"{failures} consecutive steps had a non-finite loss or gradient (last: "
                            f"{', '.join(record['bad_tensors'])}); stopped at step {self.step}. "
                            f"{self.last_checkpoint_note()}: lower the learning rates or check the data for NaN/Inf")
                    continue
                failures = 0
                good += 1
                for hook in hooks:
                    hook.after_step(self, record)
            if taken and not good:  # the model is the untrained one: nothing to save or score
                raise TrainingDiverged(
                    f"none of the {taken} steps had a finite loss and gradients (last: "
                    f"{', '.join(record['bad_tensors'])}), so nothing was trained, saved or scored: lower the "
                    "learning rates or check the data for NaN/Inf")
        finally:
            for hook in hooks:
                hook.on_end(self)

    def train(self, extra_hooks: list[TrainingHook] = ()) -> dict[str, Any]:
        """The command line's run: progress, periodic eval and checkpoints (and `extra_hooks`: the
        viewer's); then save, evaluate and write OUT/metrics.json (and renders). Ctrl-C stops after
        the step in progress, saves a checkpoint and raises TrainingInterrupted."""
        config = self.config
        hooks: list[TrainingHook] = [ProgressBar()] if not config.quiet else []
        if config.eval_every:
            hooks.append(EvaluateEvery(config.eval_every))
        hooks.append(CheckpointEvery(config.checkpoint_every))
        with interrupt_requests() as interrupt:
            # last: the step's evaluation and checkpoint come first
            hooks = [*hooks, *extra_hooks, StopWhenInterrupted(interrupt)]
            try:
                self.fit(hooks)
            except TrainingInterrupted:
                if self.saved_step != self.step:
                    self.save()
                raise TrainingInterrupted(self.step, self.checkpoint_path()) from None
            self.save()
            if self.pipeline.exposures is not None:
                write_json(config.out / "learned_exposures.json", self.pipeline.exposures.report())
        try:
            metrics = self.evaluate(save_renders=config.save_renders)
            write_json(config.out / "metrics.json", metrics)
        except KeyboardInterrupt:  # the trained model is saved: resuming only evaluates
            raise TrainingInterrupted(self.step, self.checkpoint_path()) from None
        except OSError as error:
            raise OutputError(f"{os_error_line(error)}. Training finished and its checkpoint {self.checkpoint_path()} "
                              "is saved: once fixed, score it with `mono-hdr eval --checkpoint "
                              f"{self.checkpoint_path()}`") from error
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

    def last_checkpoint_note(self) -> str:
        """Where the last good state is, for error messages: never a checkpoint that was not written."""
        if self.saved_step is None:
            return (f"No checkpoint has been written yet (--checkpoint-every {self.config.checkpoint_every}), so "
                    "nothing of this run is kept")
        return f"The last good checkpoint is {self.checkpoint_path()} (step {self.saved_step}); --resume continues it"

    def save(self) -> None:
        """Write OUT/checkpoints/latest.pt. Non-finite parameters never replace a good checkpoint, and
        a file-system error (a full disk) keeps the previous one and says so."""
        bad = [name for name, parameter in self.pipeline.named_parameters() if not torch.isfinite(parameter).all()]
        if bad:
            raise TrainingDiverged(f"parameters {', '.join(bad[:3])} became NaN or Inf by step {self.step} and are "
                                   f"not saved. {self.last_checkpoint_note()}: lower the learning rates or check the "
                                   "data for NaN/Inf")
        try:
            self._write_checkpoint()
        except OSError as error:
            raise CheckpointError(f"cannot save the checkpoint of step {self.step}: {os_error_line(error)}. "
                                  f"{self.last_checkpoint_note()}") from error
        self.saved_step = self.step

    def _write_checkpoint(self) -> None:
        save_checkpoint(self.checkpoint_path(), {
            "backbone_name": self.backbone_name,
            "config": config_to_json(self.config),
            "data": {"scene": self.scene.name, "source": str(self.scene.metadata.get("source", "in memory")),
                     "train_views": len(self.scene.train), "fingerprint": self.scene.fingerprint()},
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
        """Load model, converters, optimiser and RNG state from a checkpoint payload, after checking
        that it is this run's: same backbone, method and data (ResumeMismatch names what differs)."""
        changed = self._check_resumable(payload)
        try:
            self.pipeline.load_state_dict(payload["pipeline"])
            for group, fresh in zip(self.optimizer.param_groups, self.pipeline.parameter_groups(), strict=True):
                group["params"] = list(fresh["params"])  # the (possibly resized) parameters, before Adam's state
            self.optimizer.load_state_dict(payload["optimizer"])
        except (RuntimeError, ValueError, KeyError) as error:
            settings = f" (changed: {', '.join(changed)})" if changed else ""
            raise ResumeMismatch(f"cannot resume from {self.checkpoint_path()}: its model does not fit the one these "
                                 f"flags build{settings}: {str(error).strip().splitlines()[0][:200]}. Pass the "
                                 "flags it was trained with, or train into another --out") from error
        if changed:
            console.print(f"note: resuming with changed settings: {', '.join(changed)}", markup=False)
        self.step = payload["step"]
        self.saved_step = payload["step"]
        self.train_seconds = payload["train_seconds"]
        if self.config.max_seconds is not None:  # keep the schedule the time budget had scaled to
            self.run_length = min(payload["run_length"], self.config.max_steps)
            self.pipeline.set_run_length(self.run_length)
        self.generator.set_state(payload["generator"])
        torch.set_rng_state(payload["torch_rng"])
        self.view_order = payload["view_order"].tolist()

    def _check_resumable(self, payload: dict[str, Any]) -> list[str]:
        """Raise ResumeMismatch naming every difference that makes resuming meaningless (backbone,
        method, converter width, data); return the other changed settings, as `--flag new (was old)`."""
        if payload.get("backbone_name") != self.backbone_name:
            raise self._cannot_resume([f"the checkpoint holds a {payload.get('backbone_name')!r} model, not "
                                       f"{self.backbone_name!r}"])
        try:
            saved = config_from_dict(type(self.config), json.loads(payload["config"]))
        except (KeyError, TypeError, ValueError) as error:
            raise CheckpointError(f"{self.checkpoint_path()}: its run settings cannot be read ({error}); it was not "
                                  "written by this version: train into another --out") from error
        changes = changed_flags(saved, self.config)
        reasons = [f"it was trained with {flag} {old}, not {new}" for flag, (old, new) in changes.items()
                   if flag in RESUME_IDENTITY_FLAGS]
        data = payload.get("data")
        data_changes = [describe_change(flag, change) for flag, change in changes.items() if flag in DATA_FLAGS]
        if (data["fingerprint"] != self.scene.fingerprint()) if data else data_changes:
            trained_on = (f"scene {data['scene']!r} ({data['source']}, {data['train_views']} training views)" if data
                          else "other data")
            reasons.append(f"it was trained on {trained_on}, not on scene {self.scene.name!r} "
                           f"({self.scene.metadata.get('source', 'in memory')}, {len(self.scene.train)} training views)"
                           + (f"; changed: {', '.join(data_changes)}" if data_changes else ""))
        if reasons:
            raise self._cannot_resume(reasons)
        return [describe_change(flag, change) for flag, change in changes.items()
                if flag not in RESUME_IDENTITY_FLAGS | DATA_FLAGS]

    def _cannot_resume(self, reasons: list[str]) -> ResumeMismatch:
        return ResumeMismatch(f"cannot resume from {self.checkpoint_path()}: {'; '.join(reasons)}. Pass the flags it "
                              "was trained with to continue it, or train into another --out (or --overwrite this one)")


def changed_flags(before: TrainConfig, after: TrainConfig) -> dict[str, tuple[Any, Any]]:
    """{flag: (old, new)} of the flags that differ between two run configs (paths compared resolved,
    so `./scene` and `/abs/scene` are one), leaving out RESUME_FREE_FLAGS."""
    def comparable(value: Any) -> Any:
        return str(Path(value).resolve()) if isinstance(value, Path) else value

    old = {flag: value for flag, value, _ in iter_flags(before)}
    new = {flag: value for flag, value, _ in iter_flags(after)}
    return {flag: (old.get(flag), new.get(flag)) for flag in sorted(old.keys() | new.keys())
            if flag not in RESUME_FREE_FLAGS and comparable(old.get(flag)) != comparable(new.get(flag))}


def describe_change(flag: str, change: tuple[Any, Any]) -> str:
    return f"{flag} {change[1]} (was {change[0]})"


class ProgressBar(TrainingHook):
    """A rich progress bar with the loss and the training-view LDR PSNR."""

    def on_start(self, trainer: Trainer) -> None:
        self.progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("loss {task.fields[loss]:.4f}  LDR PSNR {task.fields[psnr]:.2f}"),
                                 TimeElapsedColumn(), console=console)
        self.task = self.progress.add_task(escape(f"{trainer.backbone_name}/{trainer.pipeline.method_name}"),
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


class StopWhenInterrupted(TrainingHook):
    """Ends training cleanly after the step Ctrl-C arrived in (Trainer.train then saves)."""

    def __init__(self, interrupt: "InterruptRequest"):
        self.interrupt = interrupt

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        if self.interrupt.requested:
            raise TrainingInterrupted(trainer.step, trainer.checkpoint_path())


class InterruptRequest:
    """Whether Ctrl-C was pressed: the first press asks training to stop after the current step (so
    the saved state is a whole step, never half an optimiser or densification update); a second
    press stops at once."""

    def __init__(self):
        self.requested = False

    def __call__(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        console.print("[yellow]Ctrl-C: stopping after this step and saving a checkpoint (press again to stop at once)")


@contextlib.contextmanager
def interrupt_requests():
    """Catch Ctrl-C as an InterruptRequest inside the block (main thread only: elsewhere signals
    cannot be caught, and Ctrl-C stays a plain KeyboardInterrupt)."""
    request = InterruptRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    previous = signal.signal(signal.SIGINT, request)
    try:
        yield request
    finally:
        signal.signal(signal.SIGINT, previous)


def run_training(config: TrainConfig, backbone_name: str,
                 train: Callable[[Trainer], dict[str, Any]] = Trainer.train) -> dict[str, Any]:
    """`mono-hdr train`: claim --out (refused while another run writes it, or when it holds an earlier
    run and neither --resume nor --overwrite says what to do), load the data, then `train` (the
    viewer's training, or plain) and score."""
    check_train_config(config)
    with claim_output(config.out, "train", TRAIN_OUTPUTS, inputs=[config.data.data], overwrite=config.overwrite,
                      keep=config.resume, keep_hint="pass --resume to continue it, ") as claim:
        trainer = build_trainer(config, backbone_name)
        claim.clear_previous()
        return train(trainer)


def build_trainer(config: TrainConfig, backbone_name: str, scene: SceneData | None = None) -> Trainer:
    """Load the scene (unless given) and set up a Trainer, resuming when asked."""
    check_train_config(config)
    if scene is None:
        from mono_hdr_plugin.data.loading import load_scene  # noqa: PLC0415

        scene = load_scene(config.data)
    trainer = Trainer(config, backbone_name, scene)
    if config.resume:
        trainer.restore(load_checkpoint(trainer.checkpoint_path()))
        console.print(f"resumed from {trainer.checkpoint_path()} at step {trainer.step}", markup=False)
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
    try:
        config = config_from_dict(train_config_for(backbone_class.config_class), json.loads(payload["config"]))
    except (KeyError, TypeError, ValueError) as error:
        raise CheckpointError(f"{checkpoint}: its run settings cannot be read by this version ({error}); "
                              "retrain, or install the version that wrote it") from error
    if data_path is not None or scene_name is not None:
        config.data = dataclasses.replace(config.data, data=data_path, scene=scene_name)
    if scene is None:
        from mono_hdr_plugin.data.loading import load_scene  # noqa: PLC0415

        scene = load_scene(config.data)
    pipeline = Pipeline.create(payload["backbone_name"], config.backbone, config.hdr, scene.scene_info(),
                               ViewExposures.from_state_dict(payload["pipeline"]))
    pipeline.set_run_length(payload["run_length"])
    try:
        pipeline.load_state_dict(payload["pipeline"])
    except (RuntimeError, KeyError) as error:
        raise CheckpointError(f"{checkpoint}: its model does not fit the {payload['backbone_name']!r} model of this "
                              f"version ({str(error).strip().splitlines()[0][:200]}); retrain, or install the version "
                              "that wrote it") from error
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
