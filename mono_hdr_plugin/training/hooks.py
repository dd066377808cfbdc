"""What the training loop calls besides the step: progress, evaluation, checkpoints, Ctrl-C."""

from __future__ import annotations

import contextlib
import math
import signal
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from mono_hdr_plugin.core.progress import PlainProgressLines, duration_text

if TYPE_CHECKING:  # annotations only: the trainer imports this module
    from mono_hdr_plugin.training.trainer import Trainer

console = Console(stderr=True)


class TrainingInterrupted(KeyboardInterrupt):
    """Ctrl-C stopped training after a finished step; `checkpoint` holds that step."""

    def __init__(self, step: int, checkpoint: Path):
        super().__init__(f"interrupted at step {step}; checkpoint saved to {checkpoint}")
        self.step, self.checkpoint = step, checkpoint


class TrainingHook:
    """Something the training loop calls: at the start, after every good step, at the end."""

    def on_start(self, trainer: Trainer) -> None:
        pass

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        pass

    def on_end(self, trainer: Trainer) -> None:
        pass


def seconds_left(trainer: Trainer) -> float | None:
    """Estimated seconds until training ends: the steps left (to --max-steps, or those that fit in what is
    left of --max-seconds) at the mean step time so far, plus the evaluations still due under --eval-every
    at the mean time of those measured. None before the first step. Coarse-to-fine steps are counted at
    their cost (a 3DGS step at 1/4 the side renders 1/16 of the pixels; with --region-pixels no more than
    the region's, regions.level_costs), so the cheap first steps of a pyramid do not promise a short run."""
    if trainer.step == 0 or trainer.train_seconds <= 0:
        return None
    pyramid, run_length = trainer.pyramid, trainer.run_length
    per_step = trainer.train_seconds / pyramid.cost(0, trainer.step, run_length)  # a full-size step's seconds
    training = pyramid.cost(trainer.step, run_length, run_length) * per_step
    if trainer.config.max_seconds is not None:
        training = min(training, max(trainer.config.max_seconds - trainer.train_seconds, 0.0))
    every, measured = trainer.config.eval_every, trainer.evaluation_seconds
    if not (every and measured):
        return training
    last_step = trainer.step + round(training / per_step)
    # EvaluateEvery runs at each multiple of --eval-every before the last step (the run scores itself at its end).
    evaluations = max(math.ceil(last_step / every) - 1 - trainer.step // every, 0)
    return training + evaluations * sum(measured) / len(measured)


class ProgressBar(TrainingHook):
    """A rich progress bar with the loss, the training-view LDR PSNR and the time left (seconds_left);
    where the output is not a terminal (a log file, CI), where rich would draw nothing until the end, a
    plain line every LOG_EVERY_SECONDS instead (core/progress.py)."""

    def on_start(self, trainer: Trainer) -> None:
        self.progress = Progress(
            TextColumn("[bold]{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("loss {task.fields[loss]:.4f}  LDR PSNR {task.fields[psnr]:.2f}"),
            TimeElapsedColumn(),
            TextColumn("about {task.fields[left]} left"),
            console=console,
        )
        self.task = self.progress.add_task(
            escape(f"{trainer.backbone_name}/{trainer.pipeline.method_name}"),
            total=trainer.run_length,
            completed=trainer.step,
            loss=math.nan,
            psnr=math.nan,
            left=duration_text(seconds_left(trainer)),
        )
        self.plain_lines = PlainProgressLines(console)
        if console.is_terminal:
            self.progress.start()
        else:
            console.print(f"training {trainer.backbone_name}/{trainer.pipeline.method_name} from step {trainer.step}")

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        left = duration_text(seconds_left(trainer))
        self.progress.update(
            self.task,
            completed=trainer.step,
            total=trainer.run_length,
            loss=record["loss"],
            psnr=record["ldr_psnr"],
            left=left,
        )
        self.plain_lines.print(
            f"step {trainer.step}/{trainer.run_length}: loss {record['loss']:.4f}, "
            f"LDR PSNR {record['ldr_psnr']:.2f} dB, {trainer.train_seconds:.0f} s, about {left} left"
        )

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
            console.print(
                f"step {trainer.step}: HDR PSNR {metrics.get('hdr_psnr') or math.nan:.2f} dB, "
                f"LDR PSNR {metrics['ldr_psnr']:.2f} dB"
            )


class CheckpointEvery(TrainingHook):
    """OUT/checkpoints/latest.pt every `steps` steps."""

    def __init__(self, steps: int):
        self.steps = steps

    def after_step(self, trainer: Trainer, record: dict[str, Any]) -> None:
        if trainer.step % self.steps == 0:
            trainer.save()


class StopWhenInterrupted(TrainingHook):
    """Ends training cleanly after the step Ctrl-C arrived in (Trainer.train then saves)."""

    def __init__(self, interrupt: InterruptRequest):
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
