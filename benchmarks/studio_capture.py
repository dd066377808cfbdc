"""HDR from a (simulated) real camera, end to end, against the studio's truth.

    python benchmarks/studio_capture.py --out outputs/studio_capture

(then copy results.{json,md} to benchmarks/results/studio_capture/)

1. The studio photographer (mono_hdr_plugin.apps.studio.shoot) photographs the training cameras of a
   built-in scene as JPEGs with EXIF: auto-exposure per view, a bracket at every 4th viewpoint,
   sensor noise; and again without exposure EXIF. The scene's test cameras are never photographed.
2. `process-data` turns each folder into a dataset (structure from motion, bracket merges; the
   renders have no lens distortion, so --camera-model SIMPLE_PINHOLE).
3. Mono-HDR-GS trains on each dataset, with exposures from EXIF or learned, and on a "perfect"
   twin of the EXIF dataset: the same LDR photos and held-out views, but the studio's cameras,
   true exposures and true HDR at the bracketed viewpoints (the initial points are the
   structure-from-motion points moved into the studio's frame, so only those three differ).
4. Every model renders the held-out cameras (moved into its frame by the similarity that maps its
   cameras onto the studio's); HDR PSNR (mu-law, each image over its own maximum) is measured
   against the studio's HDR render.

Targets: merged brackets >= 35 dB against the true HDR; learned relative exposures within 5 % of
the true ones; each capture within 3 dB of the perfect twin. Writes results.json and results.md.
"""

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import tyro
from rich.console import Console

from backbones.gs import GaussianConfig
from mono_hdr_plugin.apps.bench.runs import run_facts
from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data
from mono_hdr_plugin.apps.studio.alignment import camera_into, similarity
from mono_hdr_plugin.apps.studio.render import render_scene
from mono_hdr_plugin.apps.studio.scenes import SCENES
from mono_hdr_plugin.apps.studio.shoot import ShootConfig, ShootResult, shoot
from mono_hdr_plugin.core.metrics import hdr_metrics
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import read_exr, write_json
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer

console = Console()


@dataclass
class BenchConfig:
    """The studio capture benchmark (see the module docstring)."""

    out: Path = Path("benchmarks/results/studio_capture")
    """Where the photos, datasets, runs and results go."""
    scene: str = "textured-desk"
    """A built-in scene; textured-desk is made to be photographed (the checkered ones repeat, and
    structure from motion places few of their photos)."""
    resolution: int = 192
    """Image size (at 128 px structure from motion placed too few photos of the checkered demo)."""
    spp: int = 121
    """Samples per pixel of the studio renders (a prime's square: orthogonal-array sampling)."""
    views: int = 36
    """Studio cameras; the even ones are photographed, the odd ones held out."""
    steps: int = 2000
    """Training steps of each run."""
    max_held_out: int | None = None
    """Score at most this many held-out cameras (None: all)."""
    seed: int = 0


def studio_scene(config: BenchConfig):
    """The scene at the benchmark's own resolution and sample count, whatever the built-in defaults."""
    base = SCENES[config.scene]
    return replace(
        base,
        resolution=(config.resolution, config.resolution),
        spp=config.spp,
        rig=replace(base.rig, views=config.views),
    )


def truth_by_source(result: ShootResult) -> dict:
    return {shot.file: shot for shot in result.shots}


def merge_scores(dataset: Path, report, result: ShootResult, radiance: np.ndarray) -> list[dict]:
    """Each merged bracket against the true HDR of its viewpoint (the photos' geometry: no undistortion)."""
    truth = truth_by_source(result)
    rows = []
    for hdr_view in report.hdr_views:
        merged = read_exr(dataset / "exr" / f"{hdr_view.name.split('_')[0]}.exr")
        metrics = hdr_metrics(torch.from_numpy(merged), torch.from_numpy(radiance[truth[hdr_view.sources[0]].view]))
        true_exposures = np.array([truth[name].exposure for name in hdr_view.sources])
        ratio_error = np.array(hdr_view.exposures) / hdr_view.exposures[0] / (true_exposures / true_exposures[0]) - 1
        rows.append(
            {
                "view": hdr_view.name,
                "photos": len(hdr_view.sources),
                "hdr_psnr": metrics["hdr_psnr"],
                "hdr_psnr_gt_max": metrics["hdr_psnr_gt_max"],
                "dynamic_range_stops": hdr_view.dynamic_range_stops,
                "max_ratio_error": float(np.abs(ratio_error).max()),
            }
        )
    return rows


def sources_of(dataset: Path) -> dict[str, str]:
    """Dataset image name -> photo file name, from process-data's report."""
    report = json.loads((dataset / "process_data.json").read_text())
    return {photo["name"]: photo["source"] for photo in report["photos"]}


def alignment(data: SceneData, sources: dict[str, str], result: ShootResult, cameras):
    """The similarity mapping the dataset's camera centres onto the studio cameras they were taken from."""
    truth = truth_by_source(result)
    views = data.train + data.test
    estimated = np.array([view.camera.center.double().numpy() for view in views])
    known = np.array([cameras[truth[sources[view.name]].view].center.double().numpy() for view in views])
    transform = similarity(estimated, known)
    scale, rotation, translation = transform
    residual = np.linalg.norm(scale * estimated @ rotation.T + translation - known, axis=1)
    return transform, float(residual.max() / np.linalg.norm(known.max(0) - known.min(0)))


def perfect_twin(
    data: SceneData, sources: dict[str, str], result: ShootResult, cameras, radiance, transform
) -> SceneData:
    """The dataset with the studio's cameras, true exposures and true HDR at the bracketed viewpoints."""
    truth = truth_by_source(result)
    scale, rotation, translation = transform

    def twin(view: View) -> View:
        shot = truth[sources[view.name]]
        camera = replace(cameras[shot.view], near=view.camera.near * scale, far=view.camera.far * scale)
        hdr = torch.from_numpy(radiance[shot.view]) if view.hdr is not None else None
        return View(
            camera=camera,
            image=view.image,
            exposure=shot.exposure,
            view_id=view.view_id,
            name=view.name,
            hdr=hdr,
            stem=view.stem,
        )

    points = data.points.double().numpy() * scale @ rotation.T + translation
    low, high = points.min(0), points.max(0)
    return SceneData(
        name=f"{data.name}-perfect",
        train=[twin(v) for v in data.train],
        test=[twin(v) for v in data.test],
        bounds_min=torch.from_numpy(low).float(),
        bounds_max=torch.from_numpy(high).float(),
        points=torch.from_numpy(points).float(),
        point_colors=data.point_colors,
        metadata={},
    )


def train(data: SceneData, out: Path, config: BenchConfig) -> tuple[Trainer, float]:
    run = train_config_for(GaussianConfig)(
        backbone=GaussianConfig(),
        out=out,
        quiet=True,
        save_renders=False,
        max_steps=config.steps,
        checkpoint_every=10**9,
        seed=config.seed,
    )
    trainer = Trainer(run, "gs", data)
    started = time.perf_counter()
    trainer.fit()
    return trainer, time.perf_counter() - started


def held_out_scores(trainer: Trainer, cameras: list, radiance: np.ndarray, held_out: list[int]) -> dict:
    """HDR PSNR at the held-out studio cameras (already in the model's frame)."""
    rows = []
    with trainer.pipeline.evaluating():
        for index, camera in zip(held_out, cameras):
            output = trainer.pipeline.render(camera, trainer.scene.train[0].exposure)
            rows.append(hdr_metrics(output.hdr, torch.from_numpy(radiance[index])))
    return {key: float(np.mean([row[key] for row in rows])) for key in ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max")}


def exposure_scores(trainer: Trainer, sources: dict[str, str], result: ShootResult) -> dict | None:
    """Learned (or given) exposures of the training views, relative to the reference, against the truth."""
    exposures = trainer.pipeline.exposures
    if exposures is None:
        return None
    truth = truth_by_source(result)
    true = np.array([truth[sources[view.name]].exposure for view in trainer.scene.train])
    true = true / true[int(exposures.reference)]
    error = exposures.relative_exposures().numpy() / true - 1
    initial = np.exp(exposures.initial_log.numpy()) / true - 1  # before training: EXIF, or measured from the photos
    return {
        "learned": exposures.learned,
        "views": len(true),
        "max_error": float(np.abs(error).max()),
        "median_error": float(np.median(np.abs(error))),
        "initial_max_error": float(np.abs(initial).max()),
        "initial_median_error": float(np.median(np.abs(initial))),
        "true_span_stops": float(np.log2(true.max() / true.min())),
    }


def run(config: BenchConfig) -> dict:
    torch.manual_seed(config.seed)
    scene = studio_scene(config)
    render = render_scene(scene)
    cameras = scene.cameras()
    results: dict = {"facts": run_facts(), "config": {k: str(v) for k, v in vars(config).items()}, "captures": {}}
    for variant, exif in (("exif", True), ("no-exif", False)):
        folder = config.out / variant
        result = shoot(scene, folder / "photos", ShootConfig(exposure_exif=exif, seed=config.seed), render=render)
        write_json(folder / "truth.json", result.to_json())
        console.print(f"[bold]{variant}[/bold]: {len(result.shots)} photos, brackets at {result.bracket_views}")
        started = time.perf_counter()
        report = process_data(
            ProcessDataConfig(
                images=folder / "photos",
                out=folder / "dataset",
                overwrite=True,
                camera_model="SIMPLE_PINHOLE",
                seed=config.seed,
            ),
            console,
        )
        process_seconds = time.perf_counter() - started
        data = load_scene(DataConfig(data=folder / "dataset"))
        sources = sources_of(folder / "dataset")
        transform, pose_error = alignment(data, sources, result, cameras)
        held_out = result.held_out[: config.max_held_out]
        moved = [camera_into(cameras[i], transform, data.train[0].camera) for i in held_out]
        trainer, seconds = train(data, folder / "run", config)
        capture = {
            "photos": len(result.shots),
            "placed": len(report.registered),
            "views": len(report.views),
            "hdr_views": len(report.hdr_views),
            "process_seconds": process_seconds,
            "pose_error": pose_error,
            "merges": merge_scores(folder / "dataset", report, result, render.radiance),
            "exposures": exposure_scores(trainer, sources, result),
            "train_seconds": seconds,
            "held_out": held_out_scores(trainer, moved, render.radiance, held_out),
        }
        if exif:
            twin = perfect_twin(data, sources, result, cameras, render.radiance, transform)
            perfect, seconds = train(twin, folder / "run-perfect", config)
            results["perfect"] = {
                "train_seconds": seconds,
                "exposures": exposure_scores(perfect, sources, result),
                "held_out": held_out_scores(perfect, [cameras[i] for i in held_out], render.radiance, held_out),
            }
        results["captures"][variant] = capture
        console.print(
            f"  {variant}: HDR PSNR {capture['held_out']['hdr_psnr']:.2f} dB on {len(held_out)} held-out views"
        )
    write_json(config.out / "results.json", results)
    (config.out / "results.md").write_text(markdown(results))
    return results


def percent_pair(maximum: float, median: float) -> str:
    return f"{100 * maximum:.2f} % / {100 * median:.2f} %"


def markdown(results: dict) -> str:
    perfect = results["perfect"]["held_out"]["hdr_psnr"]
    lines = [
        f"# Studio capture, end to end ({results['config']['scene']}, {results['config']['resolution']} px, "
        f"{results['config']['steps']} steps)",
        "",
        "| data | photos | HDR views | merged HDR PSNR (min / mean) | exposure error (max / median) | "
        "held-out HDR PSNR | gap to perfect |",
        "|---|---|---|---|---|---|---|",
        f"| perfect poses, exposures, HDR | | | | | {perfect:.2f} | |",
    ]
    for variant, capture in results["captures"].items():
        merges = [row["hdr_psnr"] for row in capture["merges"]]
        exposures = capture["exposures"]
        error = (
            "-"
            if exposures is None
            else (
                f"{percent_pair(exposures['max_error'], exposures['median_error'])} (learned; measured from the photos "
                f"before training: {percent_pair(exposures['initial_max_error'], exposures['initial_median_error'])})"
                if exposures["learned"]
                else f"{percent_pair(exposures['max_error'], exposures['median_error'])} (EXIF)"
            )
        )
        psnr = capture["held_out"]["hdr_psnr"]
        lines.append(
            f"| {variant} | {capture['photos']} ({capture['placed']} placed) | {capture['hdr_views']} | "
            f"{min(merges):.2f} / {np.mean(merges):.2f} | {error} | {psnr:.2f} | {perfect - psnr:+.2f} |"
        )
    lines += [
        "",
        f"git {results['facts']['git_commit'][:10]}, {results['facts']['date']}; HDR PSNR is mu-law with "
        "each image over its own maximum; held-out views are the studio cameras never photographed.",
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    run(tyro.cli(BenchConfig))
