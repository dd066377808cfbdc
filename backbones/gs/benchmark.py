"""Rasteriser speed, side by side in one run: C++ kernel vs torch twin, 3 vs 6 channels.

Not a test: timings depend on the machine. The 3DGS backbone contributes it to `mono-hdr bench`
(`GaussianBackbone.benchmarks`): `mono-hdr bench raster --out OUT` prints a table and writes
OUT/raster.json.
"""

import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from backbones.gs.rasterizer import project_gaussians, rasterize
from backbones.gs.sh import eval_sh, view_directions
from mono_hdr_plugin.cameras import Camera, look_at
from mono_hdr_plugin.data.io import write_json


@dataclass
class BenchRasterConfig:
    """3DGS rasteriser: C++ kernel vs pure-torch twin, 3 vs 6 channels, side by side."""

    out: Path = Path("benchmarks/results")
    """Folder for raster.json."""
    repeats: int = 5
    """Timed runs per measurement (median), after a warm-up."""


def frustum_scene(gaussians: int, height: int, width: int, seed: int = 0) -> tuple[Camera, dict]:
    """Random Gaussians filling the view frustum between depths 2 and 6, SH degree 3."""
    gen = torch.Generator().manual_seed(seed)
    camera = Camera(look_at(torch.tensor([0.0, -4.0, 0.0]), torch.zeros(3)), fx=float(width), fy=float(width),
                    cx=0.5 * width, cy=0.5 * height, width=width, height=height)
    depth = 2 + 4 * torch.rand(gaussians, generator=gen)
    screen = torch.rand(gaussians, 2, generator=gen) * torch.tensor([width, height]) - torch.tensor([camera.cx, camera.cy])
    local = torch.stack([screen[:, 0] / camera.fx * depth, screen[:, 1] / camera.fy * depth, depth], -1)
    means = local @ camera.c2w[:3, :3].T + camera.c2w[:3, 3]
    return camera, {
        "means": means,
        "quats": torch.randn(gaussians, 4, generator=gen),
        "scales": torch.exp(torch.rand(gaussians, 3, generator=gen) * 1.5 - 5.0),
        "opacities": torch.rand(gaussians, generator=gen) * 0.9 + 0.05,
        "sh": torch.randn(gaussians, 16, 3, generator=gen) * 0.2,
    }


def _render_step(camera: Camera, scene: dict, backend: str, channels: int) -> Callable[[], None]:
    """One forward + backward of a full render (SH, projection, compositing) as in training."""
    leaves = {k: v.clone().requires_grad_() for k, v in scene.items()}
    weights = torch.rand(camera.height, camera.width, channels)

    def step():
        for leaf in leaves.values():
            leaf.grad = None
        colors = eval_sh(3, leaves["sh"], view_directions(leaves["means"], camera.center)) + 0.5
        values = colors.repeat(1, channels // 3) if channels > 3 else colors
        projected = project_gaussians(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      camera, backend=backend)
        image, alpha = rasterize(projected, values)
        ((image * weights).sum() + alpha.sum()).backward()

    return step


def _interleaved_medians(steps: dict[str, Callable[[], None]], repeats: int) -> dict[str, float]:
    """Median seconds of each step; the steps take turns, so load from other processes on a
    shared machine hits all of them alike."""
    for step in steps.values():
        step()  # warm-up: builds the extension, fills caches
    times = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            start = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in times.items()}


def bench_raster(out_dir: Path, sizes=((10_000, 128, 128), (50_000, 256, 256)), repeats: int = 5) -> list[dict]:
    """Time kernel vs torch twin (fwd+bwd, 3 channels) and the kernel's 3- vs 6-channel pass.

    sizes: (gaussians, height, width) triples. Each time is the median of `repeats` runs
    after one warm-up; the kernel's 3-channel pass is both kernel_fwd_bwd_s and ldr_s. Writes out_dir/raster.json (atomically) and returns its records.
    """
    from rich.console import Console
    from rich.table import Table

    records = []
    for gaussians, height, width in sizes:
        camera, scene = frustum_scene(gaussians, height, width)
        seconds = _interleaved_medians({
            "kernel": _render_step(camera, scene, "kernel", 3),
            "torch": _render_step(camera, scene, "torch", 3),
            "ldr_hdr": _render_step(camera, scene, "kernel", 6),
        }, repeats)
        kernel, reference, ldr_hdr = seconds["kernel"], seconds["torch"], seconds["ldr_hdr"]
        ldr = kernel  # the 3-channel kernel pass is the LDR-only pass
        records.append({"gaussians": gaussians, "height": height, "width": width,
                        "kernel_fwd_bwd_s": kernel, "torch_fwd_bwd_s": reference, "speedup": reference / kernel,
                        "ldr_s": ldr, "ldr_hdr_s": ldr_hdr, "hdr_overhead": ldr_hdr / ldr})

    table = Table(title=f"Gaussian rasteriser, forward + backward, median of {repeats} "
                        f"({torch.get_num_threads()} threads)")
    for column in ("Gaussians", "size", "kernel s", "torch s", "speedup", "LDR (3 ch) s", "LDR+HDR (6 ch) s",
                   "HDR overhead"):
        table.add_column(column, justify="right")
    for r in records:
        table.add_row(f"{r['gaussians']:,}", f"{r['width']}x{r['height']}", f"{r['kernel_fwd_bwd_s']:.4f}",
                      f"{r['torch_fwd_bwd_s']:.4f}", f"{r['speedup']:.1f}x", f"{r['ldr_s']:.4f}",
                      f"{r['ldr_hdr_s']:.4f}", f"{r['hdr_overhead']:.3f}x")
    Console().print(table)

    write_json(Path(out_dir) / "raster.json", records)
    return records


def bench_raster_command(config: BenchRasterConfig) -> list[dict]:
    return bench_raster(config.out, repeats=config.repeats)
