"""Rasteriser speed, side by side in one run.

Not a test: timings depend on the machine. Registered as `mono-hdr bench raster` (the
`mono_hdr.benchmarks` entry point of this package): `mono-hdr bench raster --out OUT` prints a table
and writes OUT/raster.json. On seeded random scenes (10k Gaussians at 128 x 128, 50k at 256 x 256) it times:

- forward + backward of what a training step rasterises: SH colours (degree 3) of the visible
  Gaussians, projection, compositing; 3 channels (LDR only, what other CPU rasterisers do)
  for the C++ kernel and its torch twin, and 6 channels (LDR + HDR, what Mono-HDR trains);
- render time of one view without gradients: LDR only, and with the HDR branch (L2H-CC on
  the visible Gaussians, 6 channels), as frames per second.

The scene is built exactly as OpenSplat's CPU anchor script builds its own from the same seed
(camera frame = world frame, 60 degree horizontal field of view, centres inside the frustum
at depths 2 to 6), so that script's timing can be set next to these (see
benchmarks/raster_vs_opensplat.py).
"""

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import torch

from backbones.gs.model import GaussianBackbone, GaussianConfig
from backbones.gs.rasterizer import Backend, project_gaussians, rasterize
from backbones.gs.sh import visible_colors
from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.converters import L2HColorConverter
from mono_hdr_plugin.core.registry import register_benchmark
from mono_hdr_plugin.core.validation import at_least
from mono_hdr_plugin.data.io import write_json

SIZES = ((10_000, 128, 128), (50_000, 256, 256))


@register_benchmark("raster")
@dataclass
class BenchRasterConfig:
    """3DGS rasteriser: forward + backward of a training pass (3 and 6 channels, C++ kernel and
    its torch twin) and render frame rates with and without the HDR branch."""

    out: Path = Path("benchmarks/results")
    """Folder for raster.json."""
    repeats: int = 7
    """Timed runs per measurement (median), after a warm-up."""
    torch_twin: bool = True
    """Also time the pure-torch twin (slow: seconds per pass at 50k Gaussians)."""

    flag_rules: ClassVar = {"repeats": at_least(1)}

    def run(self) -> list[dict[str, Any]]:
        return bench_raster(self.out, repeats=self.repeats, with_torch_twin=self.torch_twin)


def anchor_scene(gaussians: int, height: int, width: int, seed: int = 0) -> tuple[Camera, dict]:
    """Random Gaussians in the view frustum, SH degree 3, drawn in the anchor script's order.

    Returns the camera (identity pose, OpenCV axes) and means [N,3], log_scales [N,3] ~ N(-4, 0.5),
    quats [N,4] (unit), opacity_logits [N] ~ N(0, 1), sh [N,16,3] (DC ~ N(0, 0.5), rest ~ N(0, 0.1)).
    """
    gen = torch.Generator().manual_seed(seed)
    focal = width / (2.0 * math.tan(math.radians(60.0) / 2))
    cx, cy = width / 2.0, height / 2.0
    u = torch.rand(gaussians, generator=gen) * width
    v = torch.rand(gaussians, generator=gen) * height
    z = 2.0 + 4.0 * torch.rand(gaussians, generator=gen)
    means = torch.stack([(u - cx) * z / focal, (v - cy) * z / focal, z], -1)
    log_scales = -4.0 + 0.5 * torch.randn(gaussians, 3, generator=gen)
    quats = torch.randn(gaussians, 4, generator=gen)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    opacity_logits = torch.randn(gaussians, 1, generator=gen)[:, 0]
    sh = torch.empty(gaussians, 16, 3)
    sh[:, :1] = 0.5 * torch.randn(gaussians, 1, 3, generator=gen)
    sh[:, 1:] = 0.1 * torch.randn(gaussians, 15, 3, generator=gen)
    camera = Camera(torch.eye(4), fx=focal, fy=focal, cx=cx, cy=cy, width=width, height=height)
    return camera, {
        "means": means,
        "log_scales": log_scales,
        "quats": quats,
        "opacity_logits": opacity_logits,
        "sh": sh,
    }


def _training_pass(camera: Camera, scene: dict, backend: Backend, channels: int) -> Callable[[], None]:
    """One forward + backward as in training: activations, projection, SH, compositing."""
    leaves = {name: value.clone().requires_grad_() for name, value in scene.items() if name != "sh"}
    leaves["sh_dc"] = scene["sh"][:, :1].clone().requires_grad_()
    leaves["sh_rest"] = scene["sh"][:, 1:].clone().requires_grad_()
    weights = torch.rand(camera.height, camera.width, channels, generator=torch.Generator().manual_seed(1))

    def step():
        for leaf in leaves.values():
            leaf.grad = None
        projected = project_gaussians(
            leaves["means"],
            leaves["quats"],
            torch.exp(leaves["log_scales"]),
            torch.sigmoid(leaves["opacity_logits"]),
            camera,
            backend=backend,
        )
        colors = (
            visible_colors(
                3, leaves["sh_dc"], leaves["sh_rest"], leaves["means"], projected.index, camera.center, backend=backend
            )
            + 0.5
        ).clamp_min(0)
        values = colors if channels == 3 else torch.cat([colors, 4.0 * colors], -1)  # HDR stand-in
        image, _ = rasterize(projected, values)
        (image * weights).sum().backward()

    return step


def _render_passes(camera: Camera, scene: dict) -> dict[str, Callable[[], None]]:
    """Render one view without gradients: LDR only, and with Mono-HDR's HDR branch as its method
    renders in eval mode (L2H-CC on the visible Gaussians' colours, one 6-channel composite)."""
    info = SceneInfo(bounds_min=-torch.ones(3), bounds_max=torch.ones(3), train_cameras=[])
    backbone = GaussianBackbone(GaussianConfig(random_init_points=1), info)
    backbone.load_gaussians(
        {
            "means": scene["means"],
            "sh_dc": scene["sh"][:, :1],
            "sh_rest": scene["sh"][:, 1:],
            "log_scales": scene["log_scales"],
            "quats": scene["quats"],
            "opacity_logits": scene["opacity_logits"],
        }
    )
    backbone.active_sh_degree = 3
    l2h = L2HColorConverter().eval()

    @torch.no_grad()
    def ldr():
        features = backbone.render_ldr_features(camera)
        features.composite(features.colors)

    @torch.no_grad()
    def ldr_hdr():
        features = backbone.render_ldr_features(camera)
        hdr = l2h(features.colors if features.l2h_inputs is None else features.l2h_inputs)
        features.composite(torch.cat([features.colors, hdr], dim=-1))

    return {"render_ldr": ldr, "render_ldr_hdr": ldr_hdr}


def interleaved_medians(steps: dict[str, Callable[[], None]], repeats: int) -> dict[str, float]:
    """Median seconds of each step; the steps take turns, so load from other processes on a
    shared machine hits all of them alike."""
    for step in steps.values():
        step()  # warm-up: builds the extension, fills caches
    times: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            start = time.perf_counter()
            step()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(values) for name, values in times.items()}


def bench_raster(out_dir: Path, sizes=SIZES, repeats: int = 7, with_torch_twin: bool = True) -> list[dict]:
    """Time the passes above for each (gaussians, height, width); write out_dir/raster.json."""
    from rich.console import Console
    from rich.table import Table

    records = []
    for gaussians, height, width in sizes:
        camera, scene = anchor_scene(gaussians, height, width)
        steps = {
            "kernel_fwd_bwd_3ch": _training_pass(camera, scene, "kernel", 3),
            "kernel_fwd_bwd_6ch": _training_pass(camera, scene, "kernel", 6),
            **_render_passes(camera, scene),
        }
        if with_torch_twin:
            steps["torch_fwd_bwd_3ch"] = _training_pass(camera, scene, "torch", 3)
        seconds = interleaved_medians(steps, repeats)
        record = {
            "gaussians": gaussians,
            "height": height,
            "width": width,
            "threads": torch.get_num_threads(),
            **{f"{name}_s": value for name, value in seconds.items()},
            "hdr_channels_cost": seconds["kernel_fwd_bwd_6ch"] / seconds["kernel_fwd_bwd_3ch"],
            "fps_ldr": 1.0 / seconds["render_ldr"],
            "fps_ldr_hdr": 1.0 / seconds["render_ldr_hdr"],
            "hdr_render_cost": seconds["render_ldr_hdr"] / seconds["render_ldr"],
        }
        if with_torch_twin:
            record["twin_over_kernel"] = seconds["torch_fwd_bwd_3ch"] / seconds["kernel_fwd_bwd_3ch"]
        records.append(record)

    table = Table(title=f"Gaussian rasteriser, median of {repeats} ({torch.get_num_threads()} threads)")
    for column in (
        "Gaussians",
        "size",
        "fwd+bwd 3 ch s",
        "fwd+bwd 6 ch s",
        "6 / 3 ch",
        "torch twin 3 ch s",
        "fps LDR",
        "fps LDR+HDR",
        "HDR render cost",
    ):
        table.add_column(column, justify="right")
    for r in records:
        twin = f"{r['torch_fwd_bwd_3ch_s']:.3f}" if "torch_fwd_bwd_3ch_s" in r else "-"
        table.add_row(
            f"{r['gaussians']:,}",
            f"{r['width']}x{r['height']}",
            f"{r['kernel_fwd_bwd_3ch_s']:.4f}",
            f"{r['kernel_fwd_bwd_6ch_s']:.4f}",
            f"{r['hdr_channels_cost']:.3f}x",
            twin,
            f"{r['fps_ldr']:.0f}",
            f"{r['fps_ldr_hdr']:.0f}",
            f"{r['hdr_render_cost']:.3f}x",
        )
    Console().print(table)
    write_json(Path(out_dir) / "raster.json", records)
    return records


def time_training_pass(gaussians: int, height: int, width: int, runs: int = 5) -> dict:
    """Median seconds of `runs` forward + backward passes (3 channels, SH degree 3) on the anchor
    scene after one warm-up: the protocol of OpenSplat's anchor script, for side-by-side timing."""
    camera, scene = anchor_scene(gaussians, height, width)
    step = _training_pass(camera, scene, "kernel", 3)
    step()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return {
        "gaussians": gaussians,
        "height": height,
        "width": width,
        "fwd_bwd_s": statistics.median(times),
        "threads": torch.get_num_threads(),
    }
