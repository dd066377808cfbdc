"""What every method shares: the HdrMethod base class, the settings common to all methods, the
images a method renders and the targets it is scored against, and the registry of methods.

A method is one module: an HdrMethod subclass registered with `@register_method("name")` that
declares its own flags (`options_class`, a dataclass: `--method NAME --help` lists them), the flags
a resumed run must keep (`resume_identity_flags`) and how an exported model applies it (`hdr_recipe`).
"""

from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal

import torch
import tyro
from torch import Tensor, nn

from mono_hdr_plugin.core.backbone import OFFICIAL_CONVERTER_LR, LdrFeatures
from mono_hdr_plugin.core.calibration import well_exposed, well_exposed_channels
from mono_hdr_plugin.core.configs import SAVED_IN_PARENT
from mono_hdr_plugin.core.losses import LossKind, log_ratio_loss, photometric_loss, scale_invariant_log_loss
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.core.registry import PluginRegistry, RegistryError
from mono_hdr_plugin.core.validation import FRACTION, LOSS_WEIGHT, POSITIVE, at_least, iter_flags

# Paper defaults of the loss weights per backbone loss kind (docs/method.md).
DEFAULT_BETA = {"l1_dssim": 0.05, "mse": 0.01}
# Weight of L_log on an unbounded scene, both backbones, chosen by runs at 0 / 0.01 / 0.03 on the
# outdoor scenes (docs/outdoor.md, "The colour under a bright sky"); interiors train without it.
UNBOUNDED_HDR_LOG_WEIGHT = 0.01
# Weight of L_prior when no training view has HDR ground truth (docs/method.md, "HDR without HDR views").
HDR_PRIOR_WEIGHT = 0.1


@dataclass
class MethodOptions:
    """The flags of a method that has none of its own (the base of every method's options)."""


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
    hdr_scale_anchor: float = 0.0
    """Weight of L_anchor: L_hdr with the render and the ground truth both divided by the ground
    truth's maximum, so the HDR's absolute level is trained too (L_hdr divides each by its own
    maximum, which leaves the level free). 0: off, the paper's recipe; the radiance calibration
    sets the level of every output either way (docs/method.md, "Calibrated HDR")."""
    hdr_log_weight: float | None = None
    """Weight of L_log: the HDR render against the HDR ground truth as a relative error (log ratio, blind
    to the level) over the pixels the LDR photo exposes well, so a wrong colour away from the brightest
    pixels costs as much as one near them (on a 1e6 : 1 sky L_hdr's mu-law over the maximum puts every
    pixel but the sun's below 0.02). Default: 0.01 on an unbounded scene, else 0
    (off, the paper's recipe)."""
    hdr_prior_weight: float | None = None
    """Weight of L_prior: mean |log HDR render - log(f^-1(photo) / t)| over the channels the photo exposes
    well, f the camera response (process-data's fitted one, else sRGB) and t the view's exposure relative
    to the reference view: where no HDR view exists, the HDR is tied to the radiance the photo records
    (docs/method.md, "HDR without HDR views"). Applied to views trained without HDR ground truth. Default:
    0.1 when no training view has HDR ground truth, else 0 (the paper's recipe)."""
    beta: float | None = None
    """Weight of L_h2l; default 0.05 with the 3DGS loss, 0.01 with the NeRF loss."""
    loss: Literal["auto", "l1_dssim", "mse"] = "auto"
    """Photometric loss; auto takes the backbone's (3DGS: L1 + D-SSIM, NeRF: MSE)."""
    dssim_weight: float = 0.2
    """lambda of (1 - lambda) L1 + lambda (1 - SSIM)."""
    converter_lr: float | None = None
    """Learning rate of L2H-CC / H2L-CC / the CRF networks; default: the backbone's converter_lr
    (5e-4, hard-coded in the official codes; the NeRF cpu field: the rate of its own MLPs)."""
    # The method's own flags, an instance of its options_class (None: its defaults), flagged without a prefix.
    options: Annotated[Any, tyro.conf.OmitArgPrefixes] = None

    flag_rules: ClassVar = {
        "hidden": at_least(1),
        "alpha": LOSS_WEIGHT,
        "hdr_scale_anchor": LOSS_WEIGHT,
        "hdr_log_weight": LOSS_WEIGHT,
        "hdr_prior_weight": LOSS_WEIGHT,
        "beta": LOSS_WEIGHT,
        "dssim_weight": FRACTION,
        "converter_lr": POSITIVE,
    }

    def __post_init__(self) -> None:
        if self.options is None and self.method in METHODS.available():
            self.options = METHODS.get(self.method).options_class()


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
    radiance: Tensor | None = None
    """The radiance the photo records, f^-1(ldr) / (t / t_ref), at every pixel: L_prior's target on a view
    trained without HDR ground truth, used where the photo is well exposed (None: no prior)."""


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
    Its own flags are the fields of `options_class`, read as `self.options`.
    """

    renders_any_exposure = False
    options_class: ClassVar[type] = MethodOptions
    """A dataclass of the method's own flags (docstrings are their help, `flag_rules` their ranges);
    `mono-hdr train BACKBONE --method NAME --help` lists them."""
    resume_identity_flags: ClassVar[tuple[str, ...]] = ("--method", "--hidden")
    """Flags a resumed run must keep: changing one would continue a different model."""
    hdr_recipe: ClassVar[str | None] = None
    """How an exported model (a splat PLY) turns a Gaussian's colour into HDR with this method's
    weights, written beside the PLY by `mono-hdr export` (None: a pointer to the method's forward)."""

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__()
        self.config = config
        self.options = self.options_class() if config.options is None else config.options
        if type(self.options) is not self.options_class:
            raise TypeError(
                f"method {config.method!r} takes {self.options_class.__name__} options, not "
                f"{type(self.options).__name__}: build its config as MethodConfig(method="
                f"{config.method!r}) or with train_config_for(..., {config.method!r})"
            )
        self.loss_kind = loss_kind if config.loss == "auto" else config.loss
        self.beta = DEFAULT_BETA[loss_kind] if config.beta is None else config.beta

    @classmethod
    def own_flags(cls) -> list[str]:
        """The command-line flags of the method's own options (`--unit-exposure-weight`, ...)."""
        return [flag for flag, _, _ in iter_flags(cls.options_class())]

    def forward(self, features: LdrFeatures, exposure: float | Tensor) -> MethodOutput:
        """Images at `exposure` seconds (a tensor when the exposure is learned: gradients reach it)."""
        raise NotImplementedError

    def render(self, features: LdrFeatures, exposure: float | Tensor) -> MethodOutput:
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
        if config.hdr_scale_anchor and targets.hdr is not None:
            peak = targets.hdr.max()
            anchored = self._loss(normalise_hdr(output.hdr, peak), normalise_hdr(targets.hdr, peak))
            terms["hdr_anchor"] = config.hdr_scale_anchor * anchored
        if config.hdr_log_weight and targets.hdr is not None:
            exposed = well_exposed(targets.ldr)
            if exposed.any():
                relative = scale_invariant_log_loss(output.hdr[exposed], targets.hdr[exposed])
                terms["hdr_log"] = config.hdr_log_weight * relative
        if config.hdr_prior_weight and targets.radiance is not None:
            exposed = well_exposed_channels(targets.ldr)
            if exposed.any():
                terms["hdr_prior"] = config.hdr_prior_weight * log_ratio_loss(
                    output.hdr[exposed], targets.radiance[exposed]
                )
        return terms

    def parameter_groups(self) -> list[dict]:
        lr = OFFICIAL_CONVERTER_LR if self.config.converter_lr is None else self.config.converter_lr
        return [{"name": "method", "params": list(self.parameters()), "lr": lr}]

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        return base_lr


def _validate_method(name: str, method_class: Any) -> None:
    if not (isinstance(method_class, type) and issubclass(method_class, HdrMethod)):
        raise RegistryError(
            f"method {name!r}: {method_class!r} is not a subclass of mono_hdr_plugin.methods.base.HdrMethod"
        )


METHODS: PluginRegistry[type[HdrMethod]] = PluginRegistry("method", "mono_hdr.methods", _validate_method)
register_method = METHODS.register
"""Class decorator: make an HdrMethod subclass available as `--method <name>`."""


def build_method(config: MethodConfig, loss_kind: LossKind) -> HdrMethod:
    """The method named in the config, for a backbone whose default loss is `loss_kind`."""
    return METHODS.get(config.method)(config, loss_kind)


def method_names() -> list[str]:
    """Every registered method, built-in first."""
    return list(METHODS.available())


_METHOD_CONFIGS: dict[tuple[str, type], type] = {}


def method_config_for(name: str) -> type[MethodConfig]:
    """A MethodConfig subclass for the registered method `name`: `method` defaults to it and
    `options` has the type of its options_class, so the command line takes its own flags
    (`--unit-exposure-weight`) beside the shared ones and refuses those of other methods."""
    method_class = METHODS.get(name)
    if (name, method_class) not in _METHOD_CONFIGS:
        options_class = method_class.options_class
        _METHOD_CONFIGS[name, method_class] = dataclass(
            type(
                f"{method_class.__name__}Config",
                (MethodConfig,),
                {
                    "__annotations__": {"method": str, "options": Annotated[options_class, tyro.conf.OmitArgPrefixes]},
                    "method": name,
                    "options": field(default_factory=options_class, metadata={SAVED_IN_PARENT: True}),
                    "__doc__": MethodConfig.__doc__,
                    "__module__": MethodConfig.__module__,
                },
            )
        )
    return _METHOD_CONFIGS[name, method_class]
