"""The one training loop (any backbone, any method) and its hooks; training.trained loads what it saved.

    trainer = build_trainer(config, "gs")        # a Pipeline, Adam, the data, step and seconds
    metrics = trainer.train()                    # progress, periodic eval, checkpoints, metrics.json

`Trainer.fit(hooks)` is the loop itself: it stops at --max-steps or --max-seconds and refuses a
run that keeps producing non-finite losses; everything else (progress bar, evaluation,
checkpoints, the benchmarks' curves) is a `TrainingHook`. `run_training` is `mono-hdr train`: it
claims --out first (one run per folder, no earlier run replaced unasked; docs/robustness.md).
"""

import dataclasses
import json
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch
from rich.console import Console

from mono_hdr_plugin.core.backbone import Backbone
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.configs import config_to_json
from mono_hdr_plugin.core.exposure import build_view_exposures
from mono_hdr_plugin.core.metrics import psnr
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.errors import os_error_line
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.outputs import OutputError, claim_output
from mono_hdr_plugin.methods.base import HdrMethod, MethodConfig, Targets
from mono_hdr_plugin.training.batches import training_batch
from mono_hdr_plugin.training.calibration import fit_radiance_calibration
from mono_hdr_plugin.training.checkpoints import CheckpointError, load_checkpoint, save_checkpoint
from mono_hdr_plugin.training.config import (
    DEFAULT_MAX_STEPS,
    TRAIN_OUTPUTS,
    TrainConfig,
    check_train_config,
    hdr_supervised_views,
    parse_view_ratio,
    saved_train_config,
    step_limit,
)
from mono_hdr_plugin.training.evaluation import evaluate
from mono_hdr_plugin.training.hdr_prior import (
    camera_response,
    ground_truth_views,
    hdr_basis,
    prior_radiance,
    resolve_prior_weight,
)
from mono_hdr_plugin.training.hooks import (
    CheckpointEvery,
    EvaluateEvery,
    ProgressBar,
    StopWhenInterrupted,
    TrainingHook,
    TrainingInterrupted,
    interrupt_requests,
)
from mono_hdr_plugin.training.pipeline import Pipeline
from mono_hdr_plugin.training.poses import check_resumed_refinement, run_pose_corrections, write_refined_poses
from mono_hdr_plugin.training.pyramid import ImagePyramid, automatic_levels
from mono_hdr_plugin.training.resume import (
    DATA_FLAGS,
    ResumeMismatch,
    changed_flags,
    check_run_to_resume,
    describe_change,
    describe_data,
    steps_left_note,
)
from mono_hdr_plugin.training.visible_adam import VisibleRowAdam

console = Console(stderr=True)
# Under --max-seconds: steps before the first estimate of the run length (the first ones pay for
# compilation and caches), estimate again every this many steps, over this many recent steps.
RUN_LENGTH_WARMUP = 5
RUN_LENGTH_EVERY = 25
RUN_LENGTH_WINDOW = 50


class TrainingDiverged(RuntimeError):
    """Too many consecutive steps produced a non-finite loss or gradient, or none was finite."""


class Trainer:
    """Owns a pipeline (backbone + method), its optimiser and the data for one run."""

    def __init__(self, config: TrainConfig, backbone_name: str, scene: SceneData):
        check_train_config(config)
        self.config, self.scene = config, scene
        torch.manual_seed(config.seed)
        ldr_share, _ = parse_view_ratio(config.hdr_view_ratio)
        self.hdr_views = hdr_supervised_views(len(scene.train), config.hdr_view_ratio)
        method_config = config.hdr
        if ldr_share == 0:  # HDR-only row of the ratio study: no LDR photo is used
            method_config = MethodConfig(**{**vars(method_config), "use_ldr_loss": False, "use_h2l_loss": False})
        uses_ground_truth = any(ground_truth_views(scene, self.hdr_views))
        prior_weight = resolve_prior_weight(method_config, uses_ground_truth)
        method_config = dataclasses.replace(method_config, hdr_prior_weight=prior_weight)
        self.pipeline = Pipeline.create(
            backbone_name,
            config.backbone,
            method_config,
            scene.scene_info(),
            build_view_exposures(config.exposure, scene),
            run_pose_corrections(config.camera, scene, backbone_name),
        )
        self.prior_response = camera_response(scene, self.pipeline.exposures) if prior_weight else None
        """The response L_prior linearises photos with (None: no prior in this run)."""
        # Under --max-seconds alone this is a first guess: the measured step time replaces it.
        limit = step_limit(config)
        self.run_length = DEFAULT_MAX_STEPS if limit is None else limit
        self.pipeline.set_run_length(self.run_length)
        groups = self.pipeline.parameter_groups()
        for group in groups:
            group["base_lr"] = group["lr"]
        self.optimizer = VisibleRowAdam(groups, eps=1e-15, fused=True)  # one kernel per group, no per-tensor loop
        self.generator = torch.Generator().manual_seed(config.seed)
        levels = config.pyramid_levels or automatic_levels(scene.train, self.backbone.coarse_to_fine_pays)
        whole_images, regions = self.backbone.pixel_batch is None, config.region_pixels
        self.pyramid = ImagePyramid(scene.train, levels, config.pyramid_share, whole_images, regions)
        self.image_level: int | None = None
        """Pyramid level the backbone was last told (None: not yet; a resumed run tells it at its first step)."""
        self.view_order: list[int] = []
        self.step = 0
        self.train_seconds = 0.0
        self.evaluation_seconds: list[float] = []
        """How long each evaluation during this process took (the time left counts the ones to come)."""
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
        budget, limit = self.config.max_seconds, step_limit(self.config)
        return (limit is not None and self.step >= limit) or (budget is not None and self.train_seconds >= budget)

    def _update_run_length(self) -> None:
        """Under --max-seconds, re-estimate the steps that fit from the recent step time and tell
        the backbone when the estimate moved, so its schedules end with the budget."""
        budget = self.config.max_seconds
        if budget is None or (self.step != RUN_LENGTH_WARMUP and self.step % RUN_LENGTH_EVERY != 0):
            return
        per_step = sum(self.recent_step_seconds) / len(self.recent_step_seconds)
        remaining = max(budget - self.train_seconds, 0.0)
        estimate = self.step + max(1, int(remaining / per_step))
        limit = step_limit(self.config)
        estimate = estimate if limit is None else min(limit, estimate)
        if abs(estimate - self.run_length) > 0.02 * self.run_length:
            self.run_length = estimate
            self.pipeline.set_run_length(estimate)

    # ----------------------------------------------------------------- training
    def _next_view(self) -> int:
        if not self.view_order:  # a fresh random permutation each epoch, as 3DGS does
            self.view_order = torch.randperm(len(self.scene.train), generator=self.generator).tolist()
        return self.view_order.pop()

    def _batch(self, view: View, index: int) -> tuple[Camera, Targets]:
        """The step's camera and targets; on a view without HDR supervision, L_prior's target too."""
        batch, regions = self.backbone.pixel_batch, self.config.region_pixels
        camera, targets = training_batch(view, batch, self.hdr_views[index], self.generator, regions)
        if self.prior_response is not None and targets.hdr is None:
            exposures = self.pipeline.exposures
            relative = 1.0 if exposures is None else torch.exp(exposures.log_scale(index)).detach()
            targets.radiance = prior_radiance(targets.ldr, self.prior_response, relative)
        return camera, targets

    def _training_view(self, index: int) -> View:
        """Training view `index` at the pyramid level of this step (full size without --pyramid-levels)."""
        level = self.pyramid.level_at(self.step, self.run_length)
        if level != self.image_level:
            self.pipeline.set_image_scale(0.5**level)
            self.image_level = level
        return self.pyramid.view(index, level)

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
        view = self._training_view(index)
        camera, targets = self._batch(view, index)
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
            self.optimizer.step(self.backbone.visible_rows(features) if self.config.region_pixels else None)
            self.pipeline.after_step(self.step, features, self.optimizer)
            self.optimizer.zero_grad(set_to_none=True)
        self.step += 1
        elapsed = time.perf_counter() - started
        self.train_seconds += elapsed
        self.recent_step_seconds.append(elapsed)
        self._update_run_length()
        record: dict[str, Any] = {name: value.item() for name, value in terms.items()}
        record["loss"] = loss.item()
        record["ldr_psnr"] = psnr(output.ldr.detach().clamp(0, 1), targets.ldr)
        record.update(skipped=bool(bad), bad_tensors=bad)
        return record

    def fit(self, hooks: Sequence[TrainingHook] = ()) -> None:
        """Train until --max-steps or --max-seconds, calling `hooks` after every good step.

        A step with a non-finite loss or gradient is skipped; --nan-patience of them in a row
        raise TrainingDiverged.
        """
        failures = taken = good = 0
        bad_tensors: list[str] = []
        for hook in hooks:
            hook.on_start(self)
        try:
            while not self.finished:
                record = self.train_step()
                taken += 1
                bad_tensors = record["bad_tensors"]
                if record["skipped"]:
                    failures += 1
                    console.print(
                        f"[yellow]step {self.step}: non-finite {', '.join(record['bad_tensors'])}; step skipped"
                    )
                    if failures >= self.config.nan_patience:
                        raise TrainingDiverged(
                            f"{failures} consecutive steps had a non-finite loss or gradient (last: "
                            f"{', '.join(record['bad_tensors'])}); stopped at step {self.step}. "
                            f"{self.last_checkpoint_note()}: lower the learning rates or check the data for NaN/Inf"
                        )
                    continue
                failures = 0
                good += 1
                for hook in hooks:
                    hook.after_step(self, record)
            if taken and not good:  # the model is the untrained one: nothing to save or score
                raise TrainingDiverged(
                    f"none of the {taken} steps had a finite loss and gradients (last: "
                    f"{', '.join(bad_tensors)}), so nothing was trained, saved or scored: lower the "
                    "learning rates or check the data for NaN/Inf"
                )
        finally:
            for hook in hooks:
                hook.on_end(self)

    def train(self, extra_hooks: Sequence[TrainingHook] = ()) -> dict[str, Any]:
        """The command line's run: progress, periodic eval and checkpoints (and `extra_hooks`: the
        viewer's); then save, evaluate and write OUT/metrics.json (and renders). Ctrl-C stops after
        the step in progress, saves a checkpoint and raises TrainingInterrupted."""
        config = self.config
        if not config.quiet:
            basis = hdr_basis(self.scene, self.hdr_views, self.pipeline.exposures)
            weight = self.method.config.hdr_prior_weight
            prior = f"; L_prior weight {weight:g}" if self.prior_response is not None else ""
            extent = self.scene.metadata.get("extent_reason", "bounded")
            console.print(f"the HDR rests on: {basis}{prior}\nscene extent: {extent}", markup=False, soft_wrap=True)
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
            if self.saved_step != self.step:  # a resumed run that had nothing to train keeps its file
                self.save()
            if self.pipeline.exposures is not None:
                write_json(config.out / "learned_exposures.json", self.pipeline.exposures.report())
            write_refined_poses(self.pipeline, self.scene, config.out, self.step, config.quiet)
        try:
            metrics = self.evaluate(save_renders=config.save_renders)
            write_json(config.out / "metrics.json", metrics)
        except KeyboardInterrupt:  # the trained model is saved: resuming only evaluates
            raise TrainingInterrupted(self.step, self.checkpoint_path()) from None
        except OSError as error:
            raise OutputError(
                f"{os_error_line(error)}. Training finished and its checkpoint {self.checkpoint_path()} "
                "is saved: once fixed, score it with `mono-hdr eval --checkpoint "
                f"{self.checkpoint_path()}`"
            ) from error
        return metrics

    # --------------------------------------------------------------- evaluation
    def calibrate(self) -> None:
        """Refit the radiance scale (training.calibration) on the current model, unless it already is."""
        if self.pipeline.calibration.step != self.step:
            self.pipeline.calibration = fit_radiance_calibration(self.pipeline, self.scene, self.step, self.hdr_views)

    def evaluate(self, save_renders: bool = False) -> dict[str, Any]:
        """Test-view metrics of the current model (eval mode, HDR calibrated), with the step and
        training seconds."""
        started = time.perf_counter()
        self.calibrate()
        render_dir = self.config.out / "renders" if save_renders else None
        appearance = self.config.exposure.eval_appearance
        metrics = evaluate(
            self.pipeline, self.scene, self.config.max_eval_views, render_dir, appearance, self.config.camera.eval_pose
        )
        self.evaluation_seconds.append(time.perf_counter() - started)
        return {**metrics, "preset": self.config.preset, "steps": self.step, "train_seconds": self.train_seconds}

    # -------------------------------------------------------------- checkpoints
    def checkpoint_path(self) -> Path:
        return self.config.out / "checkpoints" / "latest.pt"

    def last_checkpoint_note(self) -> str:
        """Where the last good state is, for error messages: never a checkpoint that was not written."""
        if self.saved_step is None:
            return (
                f"No checkpoint has been written yet (--checkpoint-every {self.config.checkpoint_every}), so "
                "nothing of this run is kept"
            )
        return f"The last good checkpoint is {self.checkpoint_path()} (step {self.saved_step}); --resume continues it"

    def save(self) -> None:
        """Write OUT/checkpoints/latest.pt. Non-finite parameters never replace a good checkpoint, and
        a file-system error (a full disk) keeps the previous one and says so."""
        bad = [name for name, parameter in self.pipeline.named_parameters() if not torch.isfinite(parameter).all()]
        if bad:
            raise TrainingDiverged(
                f"parameters {', '.join(bad[:3])} became NaN or Inf by step {self.step} and are "
                f"not saved. {self.last_checkpoint_note()}: lower the learning rates or check the "
                "data for NaN/Inf"
            )
        self.calibrate()
        try:
            self._write_checkpoint()
        except OSError as error:
            raise CheckpointError(
                f"cannot save the checkpoint of step {self.step}: {os_error_line(error)}. {self.last_checkpoint_note()}"
            ) from error
        self.saved_step = self.step

    def _write_checkpoint(self) -> None:
        save_checkpoint(
            self.checkpoint_path(),
            {
                "backbone_name": self.backbone_name,
                "config": config_to_json(self.config),
                "data": {
                    "scene": self.scene.name,
                    "source": str(self.scene.metadata.get("source", "in memory")),
                    "train_views": len(self.scene.train),
                    "fingerprint": self.scene.fingerprint(),
                },
                "pipeline": self.pipeline.state_dict(),
                "optimizer": self.optimizer.state_dict(),
                "step": self.step,
                "train_seconds": self.train_seconds,
                "run_length": self.run_length,
                "generator": self.generator.get_state(),
                "torch_rng": torch.get_rng_state(),
                "view_order": torch.tensor(self.view_order, dtype=torch.long),
            },
        )

    def restore(self, payload: dict[str, Any]) -> None:
        """Load model, converters, optimiser and RNG state from a checkpoint payload, after checking
        that it is this run's: same backbone, method and data (ResumeMismatch names what differs)."""
        changed = self._check_resumable(payload)
        check_resumed_refinement(payload, self.pipeline, self.checkpoint_path())
        try:
            self.pipeline.load_state_dict(payload["pipeline"])
            fresh_groups = self.pipeline.parameter_groups()
            for group, fresh in zip(self.optimizer.param_groups, fresh_groups, strict=True):
                group["params"] = list(fresh["params"])  # the (possibly resized) parameters, before Adam's state
            self.optimizer.load_state_dict(payload["optimizer"])
            for group, fresh in zip(self.optimizer.param_groups, fresh_groups, strict=True):
                group["per_row"] = fresh.get("per_row", False)  # a checkpoint from before visible_adam lacks it
        except (RuntimeError, ValueError, KeyError) as error:
            settings = f" (changed: {', '.join(changed)})" if changed else ""
            raise ResumeMismatch(
                f"cannot resume from {self.checkpoint_path()}: its model does not fit the one these "
                f"flags build{settings}: {str(error).strip().splitlines()[0][:200]}. Pass the "
                "flags it was trained with, or train into another --out"
            ) from error
        if changed:
            console.print(f"note: resuming with changed settings: {', '.join(changed)}", markup=False)
        self.step = payload["step"]
        self.saved_step = payload["step"]
        self.train_seconds = payload["train_seconds"]
        if self.config.max_seconds is not None:  # keep the schedule the time budget had scaled to
            limit = step_limit(self.config)
            self.run_length = payload["run_length"] if limit is None else min(payload["run_length"], limit)
            self.pipeline.set_run_length(self.run_length)
        self.generator.set_state(payload["generator"])
        torch.set_rng_state(payload["torch_rng"])
        self.view_order = payload["view_order"].tolist()

    def _check_resumable(self, payload: dict[str, Any]) -> list[str]:
        """Raise ResumeMismatch naming every difference that makes resuming meaningless (backbone,
        method, converter width, data); return the other changed settings, as `--flag new (was old)`."""
        if payload.get("backbone_name") != self.backbone_name:
            raise self._cannot_resume(
                [f"the checkpoint holds a {payload.get('backbone_name')!r} model, not {self.backbone_name!r}"]
            )
        try:
            saved = saved_train_config(type(self.config.backbone), json.loads(payload["config"]))
        except (KeyError, TypeError, ValueError) as error:
            raise CheckpointError(
                f"{self.checkpoint_path()}: its run settings cannot be read ({error}); it was not "
                "written by this version: train into another --out"
            ) from error
        changes = changed_flags(saved, self.config)
        identity = set(type(self.method).resume_identity_flags)
        reasons = [
            f"it was trained with {flag} {old}, not {new}" for flag, (old, new) in changes.items() if flag in identity
        ]
        data = payload.get("data")
        data_changes = [describe_change(flag, change) for flag, change in changes.items() if flag in DATA_FLAGS]
        if (data["fingerprint"] != self.scene.fingerprint()) if data else data_changes:
            trained_on = describe_data(data["scene"], data["source"], data["train_views"]) if data else "other data"
            here = describe_data(self.scene.name, self.scene.metadata.get("source", "in memory"), len(self.scene.train))
            reasons.append(
                f"it was trained on {trained_on}, not on {here}"
                + (f"; changed: {', '.join(data_changes)}" if data_changes else "")
            )
        if reasons:
            raise self._cannot_resume(reasons)
        return [describe_change(flag, change) for flag, change in changes.items() if flag not in identity | DATA_FLAGS]

    def _cannot_resume(self, reasons: list[str]) -> ResumeMismatch:
        return ResumeMismatch(
            f"cannot resume from {self.checkpoint_path()}: {'; '.join(reasons)}. Pass the flags it "
            "was trained with to continue it, or train into another --out (or --overwrite this one)"
        )


def run_training(
    config: TrainConfig, backbone_name: str, train: Callable[[Trainer], dict[str, Any]] = Trainer.train
) -> dict[str, Any]:
    """`mono-hdr train`: claim --out (refused while another run writes it, or when it holds an earlier
    run and neither --resume nor --overwrite says what to do), load the data, then `train` (the
    viewer's training, or plain) and score."""
    check_train_config(config)
    with claim_output(
        config.out,
        "train",
        TRAIN_OUTPUTS,
        inputs=[config.data.data],
        overwrite=config.overwrite,
        keep=config.resume,
        keep_hint="pass --resume to continue it, ",
    ) as claim:
        trainer = build_trainer(config, backbone_name)
        claim.clear_previous()
        return train(trainer)


def build_trainer(config: TrainConfig, backbone_name: str, scene: SceneData | None = None) -> Trainer:
    """Load the scene (unless given) and set up a Trainer, resuming when asked."""
    check_train_config(config)
    if config.resume:  # before the (slow) data load
        check_run_to_resume(config)
    if scene is None:
        from mono_hdr_plugin.core.metrics import SSIM_WINDOW
        from mono_hdr_plugin.data.loading import load_scene

        scene = load_scene(config.data, min_side=SSIM_WINDOW)
    trainer = Trainer(config, backbone_name, scene)
    if config.resume:
        trainer.restore(load_checkpoint(trainer.checkpoint_path()))
        console.print(f"resumed from {trainer.checkpoint_path()} at step {trainer.step}", markup=False, soft_wrap=True)
        note = steps_left_note(config, trainer.step, trainer.finished, trainer.train_seconds)
        if note:
            console.print(note, markup=False, soft_wrap=True)
    return trainer
