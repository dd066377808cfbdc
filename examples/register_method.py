"""Register a new HDR method from outside the package and train it on both built-in backbones.

The method is the classical single-exposure approach Mono-HDR-3D improves on: one global,
monotone inverse tone curve per scene maps every primitive's LDR colour to HDR (no per-primitive
network, no closed loop). It is this one file: a class, its own flags (`ToneCurveOptions`: `--knots`),
the flags a resumed run must keep, the recipe an export writes, and one decorator; then
`mono-hdr train <backbone> --method tone-curve --knots 8` works on every backbone (`--method
tone-curve --help` lists --knots), and the trainer, checkpoints, evaluation and benchmarks take it
as they are.

    python examples/register_method.py --steps 200 --knots 16
"""

import argparse
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mono_hdr_plugin.core.backbone import LdrFeatures
from mono_hdr_plugin.core.losses import LossKind
from mono_hdr_plugin.core.validation import at_least
from mono_hdr_plugin.methods.base import HdrMethod, MethodConfig, MethodOutput, register_method


@dataclass
class ToneCurveOptions:
    """The tone curve's own flags (`--method tone-curve`)."""

    knots: int = 16
    """Knots of the piecewise-linear inverse tone curve (more: a finer curve)."""

    flag_rules: ClassVar = {"knots": at_least(2)}


@register_method("tone-curve")
class GlobalToneCurve(HdrMethod):
    """A global inverse tone curve learned per scene: HDR = exp(curve(LDR)) per primitive."""

    options_class = ToneCurveOptions
    resume_identity_flags = (*HdrMethod.resume_identity_flags, "--knots")  # the curve's parameters have knots - 1 rises
    hdr_recipe = (
        "colour c = the Gaussian's LDR colour; levels = [log_offset, log_offset + cumsum(softplus("
        "raw_rises))] (knots values); hdr = exp(levels interpolated linearly at c * (knots - 1)), the same "
        "curve for every channel. Composite hdr with the same alpha weights as the LDR colour."
    )
    initial_log_range = (-4.0, 4.0)
    """ln HDR of LDR 0 and LDR 1 before training: a straight line between them."""

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__(config, loss_kind)
        self.knots = self.options.knots
        low, high = self.initial_log_range
        slope = (high - low) / (self.knots - 1)
        # softplus(raw) = slope: the curve rises by `slope` per knot interval, and can only rise
        self.raw_rises = nn.Parameter(torch.full((self.knots - 1,), slope).expm1().log())
        self.log_offset = nn.Parameter(torch.tensor(low))

    def log_curve(self, ldr: Tensor) -> Tensor:
        """Monotone piecewise-linear ln HDR of LDR values in [0, 1], any shape."""
        levels = torch.cat([self.log_offset[None], self.log_offset + torch.cumsum(F.softplus(self.raw_rises), 0)])
        position = ldr.clamp(0, 1) * (self.knots - 1)
        lower = position.floor().clamp(max=self.knots - 2).long()
        fraction = position - lower
        return torch.lerp(levels[lower], levels[lower + 1], fraction)

    def forward(self, features: LdrFeatures, exposure: float) -> MethodOutput:
        hdr_colors = torch.exp(self.log_curve(features.colors))
        image = features.composite(torch.cat([features.colors, hdr_colors], dim=-1))
        return MethodOutput(ldr=image[..., :3], hdr=image[..., 3:])


def main() -> None:
    from backbones.gs import GaussianBackbone
    from backbones.nerf import NerfBackbone
    from mono_hdr_plugin.data.config import DataConfig
    from mono_hdr_plugin.data.loading import load_scene
    from mono_hdr_plugin.training.config import train_config_for
    from mono_hdr_plugin.training.trainer import Trainer

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--scene", default="demo")
    parser.add_argument("--knots", type=int, default=ToneCurveOptions.knots)
    args = parser.parse_args()
    scene = load_scene(DataConfig(scene=args.scene))
    for name, backbone_class in (("gs", GaussianBackbone), ("nerf", NerfBackbone)):
        config = train_config_for(backbone_class.config_class, "tone-curve")(
            backbone=next(iter(backbone_class.presets().values())),
            max_steps=args.steps,
            quiet=True,
            save_renders=False,
            checkpoint_every=10**9,
            max_eval_views=4,
        )
        config.hdr.options.knots = args.knots
        config.out = config.out.parent / f"tone-curve-{name}"
        trainer = Trainer(config, name, scene)
        metrics = trainer.train()
        print(
            f"{name} + tone-curve ({trainer.method.knots} knots) on {args.scene}: HDR PSNR "
            f"{metrics['hdr_psnr']:.2f} dB, LDR PSNR {metrics['ldr_psnr']:.2f} dB after {args.steps} steps "
            f"({metrics['train_seconds']:.0f} s)"
        )


if __name__ == "__main__":
    main()
