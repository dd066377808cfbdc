"""Training, evaluation and rendering of any backbone with any method."""

import dataclasses
import json
import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import torch
import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from mono_hdr_plugin.backbone import Backbone
from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.checkpoints import (config_from_dict, config_to_json, load_checkpoint, save_checkpoint,
                                         write_json)
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.methods import HdrMethod, MethodConfig, MethodOutput, Targets, build_method
from mono_hdr_plugin.metrics import (LpipsUnavailable, hdr_metrics, load_lpips, lpips_distance, psnr, ssim,
                                     tone_mapped_pair)
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


def hdr_supervised_views(num_views: int, ratio: str) -> list[bool]:
    """Which training views keep their HDR ground truth, spread evenly, for an LDR:HDR ratio."""
    ldr, hdr = parse_view_ratio(ratio)
    if hdr == 0:
        return [False] * num_views
    fraction = 1.0 if ldr <= hdr else hdr / ldr
    count = max(1, math.ceil(fraction * num_views))
    chosen = {int(i * num_views / count) for i in range(count)}
    return [i in chosen for i in range(num_views)]


def camera_chunks(backbone: Backbone, camera: Camera) -> list[Camera]:
    """The camera split into pixel batches of `backbone.render_chunk` rays (whole if None)."""
    if backbone.render_chunk is None:
        return [camera]
    return [camera.with_pixels(pixels) for pixels in camera.pixel_centers().split(backbone.render_chunk)]


def render_full(backbone: Backbone, method: HdrMethod, camera: Camera, exposure: float) -> MethodOutput:
    """Render a whole image, in chunks of `backbone.render_chunk` rays when the backbone asks."""
    parts = [method(backbone.render_ldr_features(part), exposure) for part in camera_chunks(backbone, camera)]
    shape = (camera.height, camera.width, 3)
    return MethodOutput(ldr=torch.cat([p.ldr for p in parts]).reshape(shape),
                        hdr=torch.cat([p.hdr for p in parts]).reshape(shape))


class Trainer:
    """Owns backbone, method, optimiser and data for one run."""

    def __init__(self, config: TrainConfig, backbone_name: str, scene: SceneData):
        check_train_config(config)
        self.config, self.backbone_name, self.scene = config, backbone_name, scene
        torch.manual_seed(config.seed)
        backbone_class = get_backbone(backbone_name)
        self.backbone: Backbone = backbone_class(config.backbone, scene.scene_info())
        self.run_length = config.max_steps
        self.backbone.set_run_length(self.run_length)
        ldr_share, _ = parse_view_ratio(config.hdr_view_ratio)
        method_config = config.hdr
        if ldr_share == 0:  # HDR-only row of the ratio study: no LDR photo is used
            method_config = MethodConfig(**{**vars(method_config), "use_ldr_loss": False, "use_h2l_loss": False})
        self.method = build_method(method_config, backbone_class.loss_kind)
        self.hdr_views = hdr_supervised_views(len(scene.train), config.hdr_view_ratio)
        groups = self.backbone.parameter_groups() + self.method.parameter_groups()
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
            self.backbone.set_run_length(estimate)

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

    def _set_learning_rates(self) -> None:
        for group in self.optimizer.param_groups:
            owner = self.method if group["name"] == "method" else self.backbone
            group["lr"] = owner.learning_rate(group["name"], self.step, group["base_lr"])

    def _bad_tensors(self, loss: torch.Tensor) -> list[str]:
        bad = [] if torch.isfinite(loss) else ["loss"]
        for group in self.optimizer.param_groups:
            for index, param in enumerate(group["params"]):
                if param.grad is not None and not torch.isfinite(param.grad).all():
                    bad.append(f"grad of {group['name']}[{index}] {tuple(param.shape)}")
        return bad

    def train_step(self) -> dict[str, float]:
        """One optimiser step on one training view; returns the loss terms (floats)."""
        started = time.perf_counter()
        index = self._next_view()
        view = self.scene.train[index]
        camera, targets = self._batch(view, self.hdr_views[index])
        self._set_learning_rates()
        features = self.backbone.render_ldr_features(camera)
        output = self.method.render(features, targets.exposure)
        terms = {**self.method.losses(output, targets, self.step), **self.backbone.regularisation()}
        loss = torch.stack(list(terms.values())).sum()
        loss.backward()
        bad = self._bad_tensors(loss)
        if bad:
            self.optimizer.zero_grad(set_to_none=True)
        else:
            self.optimizer.step()
            self.backbone.after_step(self.step, features, self.optimizer)
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

    def train(self) -> dict[str, Any]:
        """Run to max_steps with progress, periodic eval and checkpoints; then evaluate."""
        config = self.config
        failures = 0
        progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TextColumn("loss {task.fields[loss]:.4f}  LDR PSNR {task.fields[psnr]:.2f}"),
                            TimeElapsedColumn(), console=console, disable=config.quiet)
        with progress:
            task = progress.add_task(f"{self.backbone_name}/{config.hdr.method}", total=self.run_length,
                                     completed=self.step, loss=math.nan, psnr=math.nan)
            while not self.finished:
                record = self.train_step()
                if record["skipped"]:
                    failures += 1
                    console.print(f"[yellow]step {self.step}: non-finite {', '.join(record['bad_tensors'])}; "
                                  "step skipped")
                    if failures >= config.nan_patience:
                        raise TrainingDiverged(
                            f"{failures} consecutive steps had a non-finite loss or gradient (last: "
                            f"{', '.join(record['bad_tensors'])}); stopped at step {self.step}. The last good "
                            f"checkpoint is {config.out / 'checkpoints' / 'latest.pt'}: lower the learning "
                            "rates or check the data for NaN/Inf")
                    continue
                failures = 0
                progress.update(task, completed=self.step, total=self.run_length, loss=record["loss"],
                                psnr=record["ldr_psnr"])
                if config.eval_every and self.step % config.eval_every == 0 and not self.finished:
                    metrics = self.evaluate(save_renders=False)
                    self.history.append(metrics)
                    progress.console.print(f"step {self.step}: HDR PSNR {metrics.get('hdr_psnr', math.nan):.2f} dB, "
                                           f"LDR PSNR {metrics['ldr_psnr']:.2f} dB")
                if self.step % config.checkpoint_every == 0:
                    self.save()
        self.save()
        metrics = self.evaluate(save_renders=config.save_renders)
        write_json(config.out / "metrics.json", metrics)
        return metrics

    # --------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, save_renders: bool = False) -> dict[str, Any]:
        """Test-view metrics with backbone and method in eval mode, back to training after."""
        self.backbone.eval()
        self.method.eval()
        try:
            return evaluate(self.backbone, self.method, self.scene, self.backbone_name, self.config,
                            steps=self.step, train_seconds=self.train_seconds,
                            render_dir=self.config.out / "renders" if save_renders else None)
        finally:
            self.backbone.train()
            self.method.train()

    # -------------------------------------------------------------- checkpoints
    def checkpoint_path(self) -> Path:
        return self.config.out / "checkpoints" / "latest.pt"

    def save(self) -> None:
        save_checkpoint(self.checkpoint_path(), {
            "backbone_name": self.backbone_name,
            "config": config_to_json(self.config),
            "backbone": self.backbone.state_dict(),
            "method": self.method.state_dict(),
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
        self.backbone.load_state_dict(payload["backbone"])
        self.method.load_state_dict(payload["method"])
        _match_optimizer_groups(self.optimizer, self.backbone.parameter_groups() + self.method.parameter_groups())
        self.optimizer.load_state_dict(payload["optimizer"])
        self.step = payload["step"]
        self.train_seconds = payload["train_seconds"]
        if self.config.max_seconds is not None:  # keep the schedule the time budget had scaled to
            self.run_length = min(payload["run_length"], self.config.max_steps)
            self.backbone.set_run_length(self.run_length)
        self.generator.set_state(payload["generator"])
        torch.set_rng_state(payload["torch_rng"])
        self.view_order = payload["view_order"].tolist()


def _match_optimizer_groups(optimizer: torch.optim.Optimizer, groups: list[dict]) -> None:
    """Point the optimiser at the (possibly resized) parameters before loading its state."""
    for group, fresh in zip(optimizer.param_groups, groups, strict=True):
        group["params"] = list(fresh["params"])


@torch.no_grad()
def evaluate(backbone: Backbone, method: HdrMethod, scene: SceneData, backbone_name: str, config: TrainConfig,
             steps: int, train_seconds: float, render_dir: Path | None = None) -> dict[str, Any]:
    """Metrics on the test views: LDR at each exposure the method can render, HDR per view."""
    train_exposures = set(scene.train_exposures)
    views = [v for v in scene.test if method.renders_any_exposure or v.exposure in train_exposures]
    if not views:
        raise ValueError(f"scene {scene.name!r} has no test view at a training exposure "
                         f"({sorted(train_exposures)}) for method {config.hdr.method!r}")
    view_ids = sorted({v.view_id for v in views})[:config.max_eval_views]
    views = [v for v in views if v.view_id in set(view_ids)]
    try:
        lpips_model, lpips_skipped = load_lpips(), None
    except LpipsUnavailable as reason:
        lpips_model, lpips_skipped = None, str(reason)
    per_exposure: dict[float, list[tuple[float, float]]] = {}
    lpips_rows: dict[str, list[float]] = {"lpips_ldr": [], "lpips_hdr": []}
    hdr_rows: list[dict[str, float]] = []
    hdr_done: set[int] = set()
    for view in views:
        output = render_full(backbone, method, view.camera, view.exposure)
        ldr = output.ldr.clamp(0.0, 1.0)
        per_exposure.setdefault(view.exposure, []).append((psnr(ldr, view.image), ssim(ldr.double(), view.image.double()).item()))
        if lpips_model is not None:
            lpips_rows["lpips_ldr"].append(lpips_distance(lpips_model, ldr, view.image))
        if view.hdr is not None and view.view_id not in hdr_done:
            hdr_done.add(view.view_id)
            hdr_rows.append(hdr_metrics(output.hdr, view.hdr))
            if lpips_model is not None:
                lpips_rows["lpips_hdr"].append(lpips_distance(lpips_model, *tone_mapped_pair(output.hdr, view.hdr, "own_max")))
            if render_dir is not None:
                save_view_renders(render_dir, view, output)
    # The headline LDR figure averages the exposures the model was trained at (t1/t3/t5).
    headline = [e for e in per_exposure if e in train_exposures] or list(per_exposure)
    ldr_psnr_by_exposure = {f"{e:g}": _mean([p for p, _ in rows]) for e, rows in sorted(per_exposure.items())}
    ldr_ssim_by_exposure = {f"{e:g}": _mean([s for _, s in rows]) for e, rows in sorted(per_exposure.items())}
    metrics: dict[str, Any] = {
        "backbone": backbone_name, "method": config.hdr.method, "scene": scene.name,
        "steps": steps, "train_seconds": train_seconds,
        "ldr_psnr": _mean([ldr_psnr_by_exposure[f"{e:g}"] for e in headline]),
        "ldr_ssim": _mean([ldr_ssim_by_exposure[f"{e:g}"] for e in headline]),
        "ldr_psnr_per_exposure": ldr_psnr_by_exposure,
        "ldr_ssim_per_exposure": ldr_ssim_by_exposure,
        "test_views": len(view_ids),
    }
    for key in ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "hdr_ssim_gt_max"):
        metrics[key] = _mean([row[key] for row in hdr_rows]) if hdr_rows else None
    for key, values in lpips_rows.items():
        metrics[key] = _mean(values) if values else None
    if lpips_skipped:
        metrics["lpips_skipped"] = lpips_skipped
    return metrics


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def save_view_renders(render_dir: Path, view: View, output: MethodOutput) -> None:
    """<name>_hdr.exr (linear), <name>_ldr.png, <name>_hdr_mulaw.png (tone-mapped for display)."""
    from mono_hdr_plugin.data.io import write_exr, write_png  # noqa: PLC0415 - keeps import light
    from mono_hdr_plugin.metrics import normalise_hdr  # noqa: PLC0415

    stem = view.stem
    write_exr(render_dir / f"{stem}_hdr.exr", output.hdr.float().numpy())
    write_png(render_dir / f"{stem}_ldr.png", output.ldr.clamp(0, 1).numpy())
    write_png(render_dir / f"{stem}_hdr_mulaw.png", normalise_hdr(output.hdr).numpy())


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


def load_trained(checkpoint: Path, scene: SceneData | None = None, data_path: Path | None = None,
                 scene_name: str | None = None) -> tuple[Trainer, dict[str, Any]]:
    """A Trainer restored from a checkpoint file, on its own data unless other data is given
    (an in-memory `scene`, a dataset folder or a built-in scene name)."""
    payload = load_checkpoint(checkpoint)
    backbone_class = get_backbone(payload["backbone_name"])
    values = json.loads(payload["config"])
    train_config_class = train_config_for(backbone_class.config_class)
    config = config_from_dict(train_config_class, values)
    if data_path is not None or scene_name is not None:
        config.data = dataclasses.replace(config.data, data=data_path, scene=scene_name)
    config.resume = False
    trainer = build_trainer(config, payload["backbone_name"], scene)
    trainer.restore(payload)
    return trainer, payload


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
