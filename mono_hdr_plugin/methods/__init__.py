"""Methods that lift any backbone to HDR: Mono-HDR (the meta-algorithm), its ablations, and
the HDR-NeRF / HDR-GS style baselines, all in the same wrapper role.

A method takes a backbone's LdrFeatures for one view, renders LDR and HDR with ONE call of
`features.composite`, and computes the training loss. It never looks inside the backbone.
Methods are plugins: `@register_method("name")` on an HdrMethod subclass, or the
`mono_hdr.methods` entry-point group; `mono-hdr methods` lists them.
"""

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor, nn

from mono_hdr_plugin.core.backbone import OFFICIAL_CONVERTER_LR, LdrFeatures
from mono_hdr_plugin.core.converters import (H2LColorConverter, L2HColorConverter, PerChannelCRF, PlainH2L,
                                        PlainL2H)
from mono_hdr_plugin.core.losses import LossKind, photometric_loss
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.core.registry import PluginRegistry, RegistryError
from mono_hdr_plugin.core.validation import FRACTION, NON_NEGATIVE, POSITIVE, at_least, between

# Paper defaults of the loss weights per backbone loss kind (docs/method.md).
DEFAULT_BETA = {"l1_dssim": 0.05, "mse": 0.01}
# Largest log radiance the baselines exponentiate: exp(30) ~ 1e13 stays finite in float32.
MAX_LOG_RADIANCE = 30.0


@dataclass
class MethodConfig:
    """How LDR features become HDR, and the loss terms that train them."""

    method: str = "mono"
    """A registered method (`mono-hdr methods`): mono (L2H-CC + H2L-CC), the ablations mlp-l2h /
    mlp-h2l / no-h2l, the baselines hdr-nerf and hdr-gs (CRF of ln E + ln dt per sample /
    Gaussian, HDR composites exp(ln E); hdr-nerf adds the unit-exposure loss), or a plugin's."""
    hidden: int = 128
    """Hidden width of the converters and the baselines' CRF networks."""
    use_ldr_loss: bool = True
    """L_ldr: rendered LDR against the LDR photo."""
    use_hdr_loss: bool = True
    """L_hdr: normalised HDR render against normalised HDR ground truth (views that have it)."""
    use_h2l_loss: bool = True
    """L_h2l: H2L-CC(normalised HDR render) against the LDR photo (Mono-HDR only)."""
    alpha: float = 0.6
    """Weight of L_hdr."""
    beta: float | None = None
    """Weight of L_h2l; default 0.05 with the 3DGS loss, 0.01 with the NeRF loss."""
    loss: Literal["auto", "l1_dssim", "mse"] = "auto"
    """Photometric loss; auto takes the backbone's (3DGS: L1 + D-SSIM, NeRF: MSE)."""
    dssim_weight: float = 0.2
    """lambda of (1 - lambda) L1 + lambda (1 - SSIM)."""
    converter_lr: float | None = None
    """Learning rate of L2H-CC / H2L-CC / the CRF networks; default: the backbone's converter_lr
    (5e-4, hard-coded in the official codes; the NeRF cpu field: the rate of its own MLPs)."""
    unit_exposure_weight: float = 0.5
    """HDR-NeRF: weight of the loss pinning CRF(ln 1) to unit_exposure_value."""
    unit_exposure_value: float = 0.5
    """HDR-NeRF: CRF output at unit exposure (0.5 synthetic, 0.73 real scenes)."""
    crf_warmup_steps: int = 500
    """HDR-NeRF: the CRF learning rate ramps up linearly over these first steps (HDR-GS has no warm-up)."""

    flag_rules: ClassVar = {"hidden": at_least(1), "alpha": NON_NEGATIVE, "beta": NON_NEGATIVE,
                            "dssim_weight": FRACTION, "converter_lr": POSITIVE, "unit_exposure_weight": NON_NEGATIVE,
                            "unit_exposure_value": between(0, 1, low_open=True, high_open=True),
                            "crf_warmup_steps": NON_NEGATIVE}


@dataclass
class MethodOutput:
    """Images rendered for one view: [*shape, 3] each."""

    ldr: Tensor
    hdr: Tensor
    ldr_from_hdr: Tensor | None = None
    auxiliary_ldr: list[Tensor] = field(default_factory=list)


@dataclass
class Targets:
    """Supervision for one view (or pixel batch of it)."""

    ldr: Tensor
    exposure: float
    hdr: Tensor | None = None


def saturate_like(pred: Tensor, photo: Tensor) -> Tensor:
    """The prediction as the photo's sensor would record it: where the photo is clipped (1.0), the
    truth is anything >= 1, so a prediction above 1 there is not an error. Without this, primitives
    that see a clipped light are held at an LDR colour of 1, and a per-channel L2H-CC cannot tell
    them from a clipped coloured wall (the demo's white bulb came out blue)."""
    return torch.where(photo >= 1.0, pred.clamp(max=1.0), pred)


class HdrMethod(nn.Module):
    """Base of every method: forward renders, `losses` scores, `parameter_groups` trains.

    A subclass implements `forward(features, exposure) -> MethodOutput` (one `composite` call)
    and may extend `losses`, `parameter_groups` and `learning_rate`. Its parameters and buffers
    are saved in checkpoints (`state_dict`), so anything that shapes a render must live there.
    """

    renders_any_exposure = False

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__()
        self.config = config
        self.loss_kind = loss_kind if config.loss == "auto" else config.loss
        self.beta = DEFAULT_BETA[loss_kind] if config.beta is None else config.beta

    def forward(self, features: LdrFeatures, exposure: float | Tensor) -> MethodOutput:
        """Images at `exposure` seconds (a tensor when the exposure is learned: gradients reach it)."""
        raise NotImplementedError

    def render(self, features: LdrFeatures, exposure: float) -> MethodOutput:
        """forward plus the auxiliary renders (NeRF's coarse pass), LDR only."""
        output = self(features, exposure)
        output.auxiliary_ldr = [self(aux, exposure).ldr for aux in features.auxiliary]
        return output

    def _loss(self, pred: Tensor, target: Tensor) -> Tensor:
        return photometric_loss(pred, target, self.loss_kind, self.config.dssim_weight)

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, Tensor]:
        """Named loss terms, already weighted; the training loss is their sum."""
        config, terms = self.config, {}
        if config.use_ldr_loss:
            terms["ldr"] = self._loss(saturate_like(output.ldr, targets.ldr), targets.ldr)
            for index, aux in enumerate(output.auxiliary_ldr):
                terms[f"ldr_aux{index}"] = self._loss(saturate_like(aux, targets.ldr), targets.ldr)
        if config.use_hdr_loss and targets.hdr is not None:
            terms["hdr"] = config.alpha * self._loss(normalise_hdr(output.hdr), normalise_hdr(targets.hdr))
        return terms

    def parameter_groups(self) -> list[dict]:
        lr = OFFICIAL_CONVERTER_LR if self.config.converter_lr is None else self.config.converter_lr
        return [{"name": "method", "params": list(self.parameters()), "lr": lr}]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        return base_lr


def _validate_method(name: str, method_class: Any) -> None:
    if not (isinstance(method_class, type) and issubclass(method_class, HdrMethod)):
        raise RegistryError(f"method {name!r}: {method_class!r} is not a subclass of "
                            "mono_hdr_plugin.methods.HdrMethod")


METHODS: PluginRegistry[type[HdrMethod]] = PluginRegistry("method", "mono_hdr.methods", _validate_method)
register_method = METHODS.register
"""Class decorator: make an HdrMethod subclass available as `--method <name>`."""


@register_method("mono")
class MonoHDR(HdrMethod):
    """The meta-algorithm: L2H-CC per primitive, one compositing pass, H2L-CC closes the loop."""

    l2h_class: type[nn.Module] = L2HColorConverter
    h2l_class: type[nn.Module] | None = H2LColorConverter

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__(config, loss_kind)
        self.l2h = self.l2h_class(config.hidden)
        self.h2l = self.h2l_class(config.hidden) if self.h2l_class is not None else None

    def forward(self, features: LdrFeatures, exposure: float) -> MethodOutput:
        hdr_colors = self.l2h(features.colors if features.l2h_inputs is None else features.l2h_inputs)
        image = features.composite(torch.cat([features.colors, hdr_colors], dim=-1))
        ldr, hdr = image[..., :3], image[..., 3:]
        # H2L-CC serves the loss only: a render (eval mode) skips it
        ldr_from_hdr = self.h2l(normalise_hdr(hdr)) if self.h2l is not None and self.training else None
        return MethodOutput(ldr=ldr, hdr=hdr, ldr_from_hdr=ldr_from_hdr)

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, Tensor]:
        terms = super().losses(output, targets, step)
        if self.config.use_h2l_loss and output.ldr_from_hdr is not None:
            terms["h2l"] = self.beta * self._loss(output.ldr_from_hdr, targets.ldr)
        return terms


@register_method("mlp-l2h")
class MonoHdrPlainL2H(MonoHDR):
    """Ablation: a plain MLP of the same width instead of L2H-CC."""

    l2h_class = PlainL2H


@register_method("mlp-h2l")
class MonoHdrPlainH2L(MonoHDR):
    """Ablation: a plain MLP of the same width instead of H2L-CC."""

    h2l_class = PlainH2L


@register_method("no-h2l")
class MonoHdrOpenLoop(MonoHDR):
    """Ablation: no H2L-CC, so no closed loop (and no L_h2l)."""

    h2l_class = None


class CrfBaseline(HdrMethod):
    """Both baselines as their official renderers do it: colours are log radiance ln E; each primitive
    (NeRF sample, Gaussian) gets LDR = CRF(ln E + ln dt) and HDR = exp(ln E), composited in one pass."""

    renders_any_exposure = True

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__(config, loss_kind)
        self.crf = PerChannelCRF(config.hidden)

    def forward(self, features: LdrFeatures, exposure: float | Tensor) -> MethodOutput:
        log_radiance = features.raw_colors.clamp(max=MAX_LOG_RADIANCE)
        ldr_colors = self.crf(log_radiance + torch.log(torch.as_tensor(exposure, dtype=log_radiance.dtype)))
        image = features.composite(torch.cat([ldr_colors, torch.exp(log_radiance)], dim=-1))
        return MethodOutput(ldr=image[..., :3], hdr=image[..., 3:])


@register_method("hdr-nerf")
class HdrNerfBaseline(CrfBaseline):
    """HDR-NeRF: the shared baseline plus its unit-exposure loss pinning the CRF at ln dt = 0 and
    its CRF learning-rate warm-up."""

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, Tensor]:
        terms = super().losses(output, targets, step)
        unit = self.crf(torch.zeros(1, 3, device=output.ldr.device))
        terms["unit_exposure"] = self.config.unit_exposure_weight * torch.mean(
            (unit - self.config.unit_exposure_value) ** 2)
        return terms

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        warmup = self.config.crf_warmup_steps
        return base_lr if warmup <= 0 else base_lr * min(1.0, (step + 1) / warmup)


@register_method("hdr-gs")
class HdrGsBaseline(CrfBaseline):
    """HDR-GS: the shared baseline (tone mapper per Gaussian, HDR rasterises exp(ln E)) and nothing else."""


def build_method(config: MethodConfig, loss_kind: LossKind) -> HdrMethod:
    """The method named in the config, for a backbone whose default loss is `loss_kind`."""
    return METHODS.get(config.method)(config, loss_kind)


def method_names() -> list[str]:
    """Every registered method, built-in first."""
    return list(METHODS.available())
