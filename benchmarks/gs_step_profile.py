"""Where the time of one Mono-HDR-GS training step goes, part by part.

Trains a built-in scene with the cpu preset for `--warmup` steps (so the Gaussians reach their
budget), then times each part of a step on its own with that step's real sizes (median CPU
seconds of `--repeats` runs, one torch thread unless --threads says otherwise), and the
whole step. Prints a Markdown table; `--out FILE` writes it too.

`--side N` resizes the scene's views to N x N pixels (bilinear, as `bench cost` does: the step's
cost depends on the pixel count, not on the detail the pixels hold); `--region-pixels N` trains and
times steps on crops of about N pixels (train's --region-pixels), the parts on a crop that sees
the median number of Gaussians of nine random ones. Both
train full-size steps only (one pyramid level), as `bench cost` does.

    python benchmarks/gs_step_profile.py --scene demo --warmup 300 --repeats 11 \\
        --out benchmarks/results/gs_step_profile.md
    python benchmarks/gs_step_profile.py --scene demo --side 1600 --region-pixels 16384 \\
        --out benchmarks/results/regions/gs_step_profile_1600.md
"""

import os
import statistics
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch

from backbones.gs import GAUSSIAN_PARAMETERS, GaussianBackbone
from backbones.gs.rasterizer import project_gaussians, rasterize
from backbones.gs.sh import visible_colors
from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.apps.bench.cost import resized_scene
from mono_hdr_plugin.core.losses import l1_dssim_loss
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import View
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.batches import training_batch
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer


def cpu_median(function, repeats: int) -> float:
    function()
    times = []
    for _ in range(repeats):
        started = time.process_time()
        function()
        times.append(time.process_time() - started)
    return statistics.median(times)


def warmed_trainer(scene_name: str, warmup: int, side: int | None, region_pixels: int | None) -> Trainer:
    """Mono-HDR-GS (cpu preset) trained `warmup` steps, so the Gaussians reach their budget."""
    scene = load_scene(DataConfig(scene=scene_name))
    if side is not None:
        scene = resized_scene(scene, side, len(scene.train))
    preset = GaussianBackbone.presets()["cpu"]
    config = train_config_for(type(preset))(
        backbone=preset,
        out=Path("/tmp/gs_step_profile"),
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
        max_steps=10 * warmup,
        pyramid_levels=1,
        region_pixels=region_pixels,
    )
    trainer = Trainer(config, "gs", scene)
    for _ in range(warmup):
        trainer.train_step()
    return trainer


def profiled_view(trainer: Trainer, region_pixels: int | None, draws: int = 9) -> View:
    """Training view 0, or with region_pixels the crop (of `draws` random ones, seed 0) that sees the
    median number of Gaussians: what a typical step renders (a crop of plain wall sees a handful)."""
    view, backbone, generator = trainer.scene.train[0], trainer.backbone, torch.Generator().manual_seed(0)
    crops = []
    with torch.no_grad():
        for _ in range(draws):
            camera, targets = training_batch(view, None, True, generator, region_pixels)
            crops.append((backbone.visible_rows(backbone.render_ldr_features(camera)).numel(), camera, targets))
    _, camera, targets = sorted(crops, key=lambda entry: entry[0])[draws // 2]
    return replace(view, camera=camera, image=targets.ldr, hdr=targets.hdr)


def rasteriser_parts(
    trainer: Trainer, view: View, zero: Callable[[], None]
) -> tuple[list[tuple[str, Callable[[], None]]], torch.Tensor]:
    """Projection, SH colours and compositing of `view`, each forward + backward; and which
    Gaussians that view sees."""
    backbone, camera = trainer.backbone, view.camera
    g = {name: getattr(backbone, name) for name in GAUSSIAN_PARAMETERS}

    def activated(detach: bool) -> tuple:
        value = {name: g[name].detach() if detach else g[name] for name in ("means", "quats", "log_scales")}
        opacity = g["opacity_logits"].detach() if detach else g["opacity_logits"]
        return value["means"], value["quats"], torch.exp(value["log_scales"]), torch.sigmoid(opacity)

    def projection():
        zero()
        p = project_gaussians(*activated(detach=False), camera)
        (p.means2d.sum() + p.conics.sum() + p.depths.sum()).backward()

    index = project_gaussians(*activated(detach=False), camera).index

    def colours():
        zero()
        visible_colors(
            backbone.active_sh_degree, g["sh_dc"], g["sh_rest"], g["means"], index, camera.center
        ).sum().backward()

    detached = project_gaussians(*activated(detach=True), camera)
    values = torch.rand(index.numel(), 6, requires_grad=True)
    weights = torch.rand(camera.height, camera.width, 6)

    def compositing():
        values.grad = None
        detached.means2d.requires_grad_()
        image, _ = rasterize(detached, values)
        (image * weights).sum().backward()

    parts = [
        ("projection (C++ kernel), forward + backward", projection),
        ("SH colours of the visible Gaussians (C++), forward + backward", colours),
        ("compositing 6 channels LDR + HDR (C++), forward + backward", compositing),
    ]
    return parts, index


def method_and_optimiser_parts(
    trainer: Trainer, view: View, visible: torch.Tensor, zero: Callable[[], None]
) -> list[tuple[str, Callable[[], None]]]:
    """L2H-CC, H2L-CC with the losses, Adam (on the `visible` rows with region training, as the
    trainer steps it) and the MCMC strategy's per-step work."""
    backbone, method = trainer.backbone, trainer.method
    rows = visible if trainer.config.region_pixels else None
    ldr_colours = torch.rand(visible.numel(), 3, requires_grad=True)
    hdr_image = (torch.rand(view.camera.height, view.camera.width, 3) * 10).requires_grad_()

    def l2h():
        zero()
        method.l2h(ldr_colours).sum().backward()

    def h2l_and_losses():
        zero()
        hdr_image.grad = None
        ldr = torch.rand_like(view.image).requires_grad_()
        loss = (
            l1_dssim_loss(ldr, view.image)
            + l1_dssim_loss(normalise_hdr(hdr_image), normalise_hdr(view.hdr))
            + l1_dssim_loss(method.h2l(normalise_hdr(hdr_image)), view.image)
        )
        loss.backward()

    def adam():
        for group in trainer.optimizer.param_groups:
            for parameter in group["params"]:
                parameter.grad = torch.zeros_like(parameter)
        trainer.optimizer.step(rows)

    def strategy():
        backbone.config.strategy.add_position_noise(backbone, 1e-5)
        backbone.regularisation()

    return [
        ("L2H-CC on the visible Gaussians, forward + backward", l2h),
        ("H2L-CC and the three L1 + D-SSIM losses, forward + backward", h2l_and_losses),
        ("Adam (fused; with crops the per-Gaussian rows the crop saw)", adam),
        ("MCMC position noise and regularisers", strategy),
    ]


def profile(
    scene_name: str, warmup: int, repeats: int, side: int | None, region_pixels: int | None
) -> tuple[list[tuple[str, float]], dict]:
    trainer = warmed_trainer(scene_name, warmup, side, region_pixels)
    backbone, view = trainer.backbone, profiled_view(trainer, region_pixels)
    camera = view.camera

    def zero():
        for name in GAUSSIAN_PARAMETERS:
            getattr(backbone, name).grad = None
        for value in trainer.method.parameters():
            value.grad = None

    parts, visible = rasteriser_parts(trainer, view, zero)
    parts += method_and_optimiser_parts(trainer, view, visible, zero)
    seconds = [(name, cpu_median(function, repeats)) for name, function in parts]
    step = cpu_median(trainer.train_step, repeats)
    facts = {
        "scene": scene_name,
        "gaussians": backbone.num_gaussians,
        "visible": visible.numel(),
        "pixels": camera.width * camera.height,
        "frame": camera.frame_size,
        "step": step,
        "threads": torch.get_num_threads(),
        "load": os.getloadavg()[0],
    }
    return seconds, facts


def table(seconds: list[tuple[str, float]], facts: dict) -> str:
    width, height = facts["frame"]
    rendered = "the whole view" if facts["pixels"] == width * height else "a crop of the view"
    lines = [
        f"Scene `{facts['scene']}` at {width} x {height} px; a step renders {rendered}, "
        f"{facts['pixels']} pixels; {facts['gaussians']:,} Gaussians of which "
        f"{facts['visible']:,} visible in the view; {facts['threads']} torch thread(s), median CPU time; "
        f"1-minute load average {facts['load']:.1f} when measured.",
        "",
        "| part of a step | ms | share of the step |",
        "|---|---|---|",
    ]
    for name, value in seconds:
        lines.append(f"| {name} | {1000 * value:.1f} | {100 * value / facts['step']:.0f} % |")
    rest = facts["step"] - sum(value for _, value in seconds)
    lines.append(
        f"| everything else (Python, autograd bookkeeping, view loading, logging) | {1000 * rest:.1f} | "
        f"{100 * rest / facts['step']:.0f} % |"
    )
    lines.append(f"| **whole training step** | **{1000 * facts['step']:.1f}** | 100 % |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = args_of.script_parser(__doc__)
    args_of.add_scenes(parser, "demo")
    args_of.add_count(parser, "--warmup", 300, "training steps before timing")
    args_of.add_count(parser, "--repeats", 15, "timed steps (median)")
    args_of.add_threads(parser, 1)
    parser.add_argument("--side", type=int, help="resize the views to SIDE x SIDE pixels")
    parser.add_argument("--region-pixels", type=int, help="train on crops of about this many pixels")
    parser.add_argument("--out", type=Path, help="also write the table here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    text = table(*profile(args.scene, args.warmup, args.repeats, args.side, args.region_pixels))
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
