"""Per-view white balance (--learn-white-balance) on a studio scene whose photos drift in white balance.

Every photo, training and held-out, is given its own white balance: log gains drawn per channel with
standard deviation SIGMA, seeded, made zero-mean over the channels (a colour, not a brightness) and,
for the training views, over the views (so the scene's colour is the photos' mean, the gauge the model
learns in), applied in linear light through the capture's response. Three runs of one backbone, the
same steps and seed: the photos as rendered ("no drift", white balance off), the drifted photos with
white balance off and on. Each is scored on the held-out views both ways: as given (rendered at the
mean balance) and with the appearance protocol (exposure and gains fitted on the left half of each
photo, PSNR/SSIM on the right half: training.appearance). Written: OUT/<backbone>.json and .md, with
the learned gains' error against the truth.

    python benchmarks/white_balance_drift.py --backbone gs --scene demo --steps 1000 --sigma 0.1
"""

import argparse
import dataclasses
import math
import sys
import tempfile
import time
from pathlib import Path

import torch

from mono_hdr_plugin.core.exposure import ExposureConfig, brighten
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.hdr_prior import camera_response
from mono_hdr_plugin.training.trainer import Trainer


def drift_gains(views: int, sigma: float, generator: torch.Generator, centred_over_views: bool) -> torch.Tensor:
    """[views, 3] log gains ~ N(0, sigma), zero mean over channels (and over views when asked)."""
    logs = torch.randn(views, 3, generator=generator, dtype=torch.float64) * sigma
    if centred_over_views:
        logs -= logs.mean(0)
    return logs - logs.mean(1, keepdim=True)


def with_gains(views: list[View], logs: torch.Tensor, response: torch.Tensor) -> list[View]:
    return [
        dataclasses.replace(view, image=brighten(view.image, log.float(), response)) for view, log in zip(views, logs)
    ]


def drifted(scene: SceneData, sigma: float, seed: int) -> tuple[SceneData, torch.Tensor]:
    """The scene with every photo under its own white balance; the training views' true log gains."""
    generator = torch.Generator().manual_seed(seed)
    response = camera_response(scene, None)
    train_logs = drift_gains(len(scene.train), sigma, generator, centred_over_views=True)
    test_logs = drift_gains(len(scene.test), sigma, generator, centred_over_views=False)
    train, test = with_gains(scene.train, train_logs, response), with_gains(scene.test, test_logs, response)
    return dataclasses.replace(scene, train=train, test=test), train_logs


def train_run(args: argparse.Namespace, scene: SceneData, white_balance: str, out: Path) -> tuple[Trainer, dict]:
    """Train the backbone (its default preset) quietly, LDR views only, and score both protocols."""
    backbone_config = next(iter(get_backbone(args.backbone).presets().values()))
    config = train_config_for(type(backbone_config))(
        backbone=backbone_config,
        out=out,
        max_steps=args.steps,
        seed=args.seed,
        hdr_view_ratio=args.hdr_view_ratio,
        exposure=ExposureConfig(learn_white_balance=white_balance, eval_appearance="on"),
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
    )
    trainer = Trainer(config, args.backbone, scene)
    started = time.perf_counter()
    trainer.fit()
    metrics = trainer.evaluate()
    metrics["wall_seconds"] = time.perf_counter() - started
    return trainer, metrics


def gain_errors(trainer: Trainer, truth: torch.Tensor) -> dict[str, float]:
    """RMS and largest error of the learned log gains against the truth (both in the same gauge)."""
    exposures = trainer.pipeline.exposures
    assert exposures is not None and exposures.white_balance is not None
    error = torch.log(exposures.white_balance.gains()).double() - truth
    return {"log_gain_rms": float(error.square().mean().sqrt()), "log_gain_max": float(error.abs().max())}


SCORES = ("ldr_psnr", "ldr_ssim", "ldr_psnr_appearance_fitted", "ldr_ssim_appearance_fitted", "hdr_psnr")


def write_report(args: argparse.Namespace, results: dict, truth: torch.Tensor, out: Path) -> None:
    command = "python benchmarks/white_balance_drift.py " + " ".join(sys.argv[1:])
    spread = float(truth.square().mean().sqrt())
    lines = [
        f"# White balance drift: {args.backbone} on {args.scene}, {args.steps} steps",
        "",
        f"`{command}`",
        "",
        f"Every photo under its own white balance: log gains with sigma {args.sigma:g} per channel (training "
        f"views' RMS {spread:.3f}), zero mean over channels, the training views' also over the views. "
        f"Training views LDR only (--hdr-view-ratio {args.hdr_view_ratio}). Held-out views scored as given "
        "(rendered at the mean balance) and with the appearance protocol (exposure and gains fitted on the "
        "left half of each photo, scored on the right half).",
        "",
        "| run | LDR PSNR as given | SSIM | LDR PSNR appearance fitted | SSIM | HDR PSNR | log gains RMS error | s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, row in results.items():
        scores = " | ".join("-" if row.get(key) is None else f"{row[key]:.4g}" for key in SCORES)
        error = f"{row['gain_errors']['log_gain_rms']:.4f}" if "gain_errors" in row else "-"
        lines.append(f"| {name} | {scores} | {error} | {row['wall_seconds']:.0f} |")
    (out / f"{args.backbone}.md").write_text("\n".join(lines) + "\n")
    write_json(out / f"{args.backbone}.json", {"command": command, "args": vars(args), "runs": results})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backbone", default="gs")
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--sigma", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--hdr-view-ratio", default="1:0")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/white_balance"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    clean = load_scene(DataConfig(scene=args.scene))
    scene, truth = drifted(clean, args.sigma, args.seed)
    runs = {"no drift, white balance off": (clean, "off"), "drift, white balance off": (scene, "off")}
    runs["drift, white balance on"] = (scene, "on")
    results: dict = {}
    with tempfile.TemporaryDirectory() as scratch:
        for index, (name, (data, white_balance)) in enumerate(runs.items()):
            trainer, metrics = train_run(args, data, white_balance, Path(scratch) / str(index))
            row = {key: metrics.get(key) for key in (*SCORES, "appearance_protocol", "steps", "wall_seconds")}
            if white_balance == "on":
                row["gain_errors"] = gain_errors(trainer, truth)
            results[name] = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in row.items()}
            print(name, {key: row[key] for key in SCORES}, flush=True)
    write_report(args, results, truth, args.out)


if __name__ == "__main__":
    main()
