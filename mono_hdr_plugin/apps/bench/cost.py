"""`mono-hdr bench cost`: what a training step, a render and an evaluation cost against image size and views.

The images are a built-in 128 px scene resized to each size (bilinear; the cameras' intrinsics scaled
to match) and its training views repeated up to each count: the content stays, the cost is that of the
larger data, and no size needs its own Mitsuba render. Each row runs in a fresh process, so its peak
memory is its own. Quality at real sizes is `bench curves --resolution N`.
"""

import multiprocessing
import statistics
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import torch
from rich.progress import Progress

from mono_hdr_plugin.apps.bench.report import fmt, pyplot, report_on_exit
from mono_hdr_plugin.apps.bench.runs import (
    RowStore,
    RunBudget,
    RunSpec,
    build_run,
    cached_scene,
    console,
    peak_memory_mib,
)
from mono_hdr_plugin.core.registry import register_benchmark
from mono_hdr_plugin.core.validation import MAX_IMAGE_SIDE, at_least, between
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.training.regions import MIN_REGION_PIXELS


@register_benchmark("cost")
@dataclass
class BenchCostConfig:
    """ms per training step, render and evaluation time and peak memory against image size and training views."""

    out: Path = Path("benchmarks/results/cost")
    """Folder for cost.json, cost.md and cost.png."""
    backbones: tuple[str, ...] = ("gs", "nerf")
    sizes: tuple[int, ...] = (128, 256, 512, 800)
    """Image sides in pixels (square images)."""
    views: tuple[int, ...] = (18, 108)
    """Training-view counts (the scene's views repeated)."""
    scene: str = "demo"
    """The built-in scene whose 128 px render is resized."""
    warmup_steps: int = 3
    """Steps not timed (the first ones allocate and build caches)."""
    timed_steps: int = 10
    """Steps whose median time is reported."""
    threads: int = 2
    """torch threads per row."""
    region_pixels: int | None = None
    """Train on random crops of about this many pixels (train's --region-pixels; 3DGS only). None: whole images."""

    flag_rules: ClassVar = {
        "sizes": between(16, MAX_IMAGE_SIDE),
        "views": at_least(1),
        "warmup_steps": at_least(0),
        "timed_steps": at_least(1),
        "threads": at_least(1),
        "region_pixels": between(MIN_REGION_PIXELS, MAX_IMAGE_SIDE**2),
    }

    def run(self) -> dict[str, Any]:
        return bench_cost(self)


def resized_view(view: View, side: int) -> View:
    """`view` resized to side x side pixels (bilinear), its camera's intrinsics scaled to match."""

    def resize(image: torch.Tensor) -> torch.Tensor:
        batch = image.permute(2, 0, 1)[None]
        return torch.nn.functional.interpolate(batch, size=(side, side), mode="bilinear")[0].permute(1, 2, 0)

    factor = side / view.camera.width
    camera = replace(view.camera.scaled(factor), width=side, height=side)
    return replace(view, camera=camera, image=resize(view.image), hdr=None if view.hdr is None else resize(view.hdr))


def resized_scene(scene: SceneData, side: int, train_views: int) -> SceneData:
    """`scene` at side x side pixels with `train_views` training views (repeated in order), one test view.

    Each view has its own tensors, as loaded data would."""
    train = [resized_view(scene.train[index % len(scene.train)], side) for index in range(train_views)]
    return replace(scene, train=train, test=[resized_view(scene.test[0], side)])


def held_mib(scene: SceneData) -> float:
    """MiB of the images and HDR ground truth the scene holds."""
    tensors = [t for view in scene.train + scene.test for t in (view.image, view.hdr) if t is not None]
    return sum(t.numel() * t.element_size() for t in tensors) / 2**20


def row_key(backbone: str, side: int, train_views: int) -> str:
    return f"{backbone}|{side}px|{train_views}views"


def cost_row(backbone: str, side: int, train_views: int, config: BenchCostConfig) -> dict[str, Any]:
    """One row, measured in the process that calls it (`bench_cost` gives each its own)."""
    torch.set_num_threads(config.threads)
    scene = resized_scene(cached_scene(config.scene, 1), side, train_views)
    peaks = {"data": peak_memory_mib()}
    budget = RunBudget(steps=config.warmup_steps + config.timed_steps, max_eval_views=1)
    overrides = (("pyramid_levels", 1), ("region_pixels", config.region_pixels))  # no coarse level
    full_size = RunSpec(backbone=backbone, scene=config.scene, overrides=overrides)
    trainer = build_run(full_size, scene, config.out / "runs", budget)
    trainer.fit([])
    step_seconds = list(trainer.recent_step_seconds)[config.warmup_steps :]
    peaks["training"] = peak_memory_mib()
    started = time.perf_counter()
    trainer.pipeline.render(scene.test[0].camera, scene.test[0].exposure)
    render_seconds = time.perf_counter() - started
    peaks["render"] = peak_memory_mib()
    started = time.perf_counter()
    trainer.evaluate()
    evaluate_seconds = time.perf_counter() - started
    peaks["evaluation"] = peak_memory_mib()
    return {
        "key": row_key(backbone, side, train_views),
        "backbone": backbone,
        "side": side,
        "train_views": train_views,
        "status": "ok",
        "ms_per_step": 1000 * statistics.median(step_seconds),
        "render_seconds": render_seconds,
        "evaluate_seconds": evaluate_seconds,
        "data_mib": held_mib(scene),
        "peak_mib": peaks,
        "backbone_statistics": trainer.backbone.statistics(),
        "threads": torch.get_num_threads(),
    }


def bench_cost(config: BenchCostConfig) -> dict[str, Any]:
    grid = [(b, s, v) for b in config.backbones for s in config.sizes for v in config.views]
    names = ("scene", "warmup_steps", "timed_steps", "threads", "region_pixels")
    measure = {name: getattr(config, name) for name in names}
    store = RowStore(config.out / "cost.json", measure)  # rows of the same measure are kept; new cells added
    pending = [cell for cell in grid if row_key(*cell) not in store.rows]
    context = multiprocessing.get_context("spawn")  # a fresh process per row: its peak memory is its own
    with report_on_exit(lambda: write_cost_report(store, config.out)), Progress(console=console) as progress:
        task = progress.add_task("cost rows", total=len(pending))
        for backbone, side, train_views in pending:
            progress.update(task, description=f"{backbone} {side} px, {train_views} views")
            try:
                with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
                    store.add(pool.submit(cost_row, backbone, side, train_views, config).result())
            except Exception as error:  # noqa: BLE001 - a row that fails (out of memory, say) is recorded, not dropped
                console.print(f"[yellow]{row_key(backbone, side, train_views)} failed: {error!r}")
                store.add({"key": row_key(backbone, side, train_views), "status": "failed", "error": repr(error)})
            progress.advance(task)
    return {"facts": store.facts, "rows": store.rows}


def write_cost_report(store: RowStore, out: Path) -> None:
    rows = sorted(
        (r for r in store.rows.values() if r["status"] == "ok"),
        key=lambda r: (r["backbone"], r["train_views"], r["side"]),
    )
    region = store.settings.get("region_pixels")
    lines = [
        f"Training steps on {'whole images' if region is None else f'random crops of about {region} pixels'}.",
        "",
        "| backbone | side | views | ms / step | step / smallest side's | pixels / smallest side's "
        "| step / fewest views' | Gaussians | render s | evaluate s | data MiB "
        "| peak MiB (data / training / render / evaluation) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        smallest = next(r for r in rows if r["backbone"] == row["backbone"] and r["train_views"] == row["train_views"])
        fewest = min(
            (r for r in rows if r["backbone"] == row["backbone"] and r["side"] == row["side"]),
            key=lambda r: r["train_views"],
        )
        peaks = " / ".join(f"{row['peak_mib'][phase]:.0f}" for phase in ("data", "training", "render", "evaluation"))
        lines.append(
            f"| {row['backbone']} | {row['side']} | {row['train_views']} | {row['ms_per_step']:.0f} | "
            f"{fmt(row['ms_per_step'] / smallest['ms_per_step'])} | {fmt((row['side'] / smallest['side']) ** 2, 1)} | "
            f"{fmt(row['ms_per_step'] / fewest['ms_per_step'])} | {row['backbone_statistics'].get('gaussians', '')} | "
            f"{row['render_seconds']:.2f} | "
            f"{row['evaluate_seconds']:.2f} | {row['data_mib']:.0f} | {peaks} |"
        )
    (out / "cost.md").write_text("\n".join(lines) + "\n")
    plot_cost(rows, out / "cost.png")


def plot_cost(rows: list[dict[str, Any]], path: Path) -> None:
    plt = pyplot()
    figure, (steps, memory) = plt.subplots(1, 2, figsize=(11, 4))
    for backbone in sorted({r["backbone"] for r in rows}):
        for views in sorted({r["train_views"] for r in rows}):
            line = [r for r in rows if r["backbone"] == backbone and r["train_views"] == views]
            pixels = [r["side"] ** 2 / 1e6 for r in line]
            name = f"{backbone}, {views} views"
            steps.plot(pixels, [r["ms_per_step"] for r in line], "o-", label=name)
            memory.plot(pixels, [r["peak_mib"]["evaluation"] for r in line], "o-", label=name)
    for axis, title in ((steps, "ms per training step"), (memory, "peak memory (MiB)")):
        axis.set(xscale="log", yscale="log", xlabel="megapixels per view", title=title)
        axis.grid(True, which="both", alpha=0.3)
        axis.legend(fontsize=8)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
