"""Where the time of one Mono-HDR-GS training step goes, part by part.

Trains a built-in scene with the cpu preset for `--warmup` steps (so the Gaussians reach their
budget), then times each part of a step on its own with that step's real sizes (median CPU
seconds of `--repeats` runs, one torch thread unless --threads says otherwise), and the
whole step. Prints a Markdown table; `--out FILE` writes it too.

    python benchmarks/gs_step_profile.py --scene demo --warmup 300 --repeats 11 \\
        --out benchmarks/results/gs_step_profile.md
"""

import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch

from backbones.gs import GAUSSIAN_PARAMETERS, GaussianBackbone
from backbones.gs.rasterizer import project_gaussians, rasterize
from backbones.gs.sh import visible_colors
from mono_hdr_plugin.apps.bench import script_args as args_of
from mono_hdr_plugin.core.losses import l1_dssim_loss
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene
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


def warmed_trainer(scene_name: str, warmup: int) -> Trainer:
    """Mono-HDR-GS (cpu preset) trained `warmup` steps, so the Gaussians reach their budget."""
    scene = load_scene(DataConfig(scene=scene_name))
    preset = GaussianBackbone.presets()["cpu"]
    config = train_config_for(type(preset))(
        backbone=preset,
        out=Path("/tmp/gs_step_profile"),
        quiet=True,
        save_renders=False,
        checkpoint_every=10**9,
        max_steps=10 * warmup,
    )
    trainer = Trainer(config, "gs", scene)
    for _ in range(warmup):
        trainer.train_step()
    return trainer


def rasteriser_parts(trainer: Trainer, zero: Callable[[], None]) -> tuple[list[tuple[str, Callable[[], None]]], int]:
    """Projection, SH colours and compositing of training view 0, each forward + backward; and how
    many Gaussians that view sees."""
    backbone, camera = trainer.backbone, trainer.scene.train[0].camera
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
    return parts, int(index.numel())


def method_and_optimiser_parts(
    trainer: Trainer, visible: int, zero: Callable[[], None]
) -> list[tuple[str, Callable[[], None]]]:
    """L2H-CC, H2L-CC with the losses, Adam and the MCMC strategy's per-step work."""
    backbone, method, view = trainer.backbone, trainer.method, trainer.scene.train[0]
    ldr_colours = torch.rand(visible, 3, requires_grad=True)
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
        trainer.optimizer.step()

    def strategy():
        backbone.config.strategy.add_position_noise(backbone, 1e-5)
        backbone.regularisation()

    return [
        ("L2H-CC on the visible Gaussians, forward + backward", l2h),
        ("H2L-CC and the three L1 + D-SSIM losses, forward + backward", h2l_and_losses),
        ("Adam (fused), all parameters", adam),
        ("MCMC position noise and regularisers", strategy),
    ]


def profile(scene_name: str, warmup: int, repeats: int) -> tuple[list[tuple[str, float]], dict]:
    trainer = warmed_trainer(scene_name, warmup)
    backbone, camera = trainer.backbone, trainer.scene.train[0].camera

    def zero():
        for name in GAUSSIAN_PARAMETERS:
            getattr(backbone, name).grad = None
        for value in trainer.method.parameters():
            value.grad = None

    parts, visible = rasteriser_parts(trainer, zero)
    parts += method_and_optimiser_parts(trainer, visible, zero)
    seconds = [(name, cpu_median(function, repeats)) for name, function in parts]
    step = cpu_median(trainer.train_step, repeats)
    facts = {
        "scene": scene_name,
        "gaussians": backbone.num_gaussians,
        "visible": visible,
        "pixels": camera.width * camera.height,
        "step": step,
        "threads": torch.get_num_threads(),
        "load": os.getloadavg()[0],
    }
    return seconds, facts


def table(seconds: list[tuple[str, float]], facts: dict) -> str:
    lines = [
        f"Scene `{facts['scene']}`, {facts['pixels']} pixels, {facts['gaussians']:,} Gaussians of which "
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
    parser.add_argument("--out", type=Path, help="also write the table here")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    text = table(*profile(args.scene, args.warmup, args.repeats))
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
