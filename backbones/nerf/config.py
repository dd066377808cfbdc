"""Hyper-parameters of the NeRF backbone: one dataclass per field, one on top holding either.

Each field config carries its own sampling and optimiser settings. Which one a run uses is the
preset's choice (`--preset cpu`, the default, or `--preset paper`); its settings are then flags
under `--backbone.field.*` (`--backbone.field.max-resolution`, `--backbone.field.coarse-samples`).
"""

import dataclasses
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

import tyro

from mono_hdr_plugin.core.configs import ABSENT_IN_SAVED_CONFIG
from mono_hdr_plugin.core.validation import ANY_FINITE, FRACTION, NON_NEGATIVE, POSITIVE, at_least, between

DensityActivation = Literal["relu", "softplus", "exp"]
ColorActivation = Literal["sigmoid", "softplus"]
L2hInput = Literal["raw", "activated"]


@dataclass
class MlpFieldConfig:
    """The official NeRF MLP and its hierarchical sampling (Mildenhall et al. 2020)."""

    depth: int = 8
    """Layers of the position MLP."""
    width: int = 256
    """Hidden width of the position MLP (the view head has width // 2)."""
    skip_layer: int = 4
    """The encoded position is concatenated to the output of this layer (0-based)."""
    xyz_frequencies: int = 10
    """Positional-encoding frequencies of the position."""
    dir_frequencies: int = 4
    """Positional-encoding frequencies of the viewing direction."""
    density_activation: DensityActivation = "relu"
    """relu as in the official code; softplus never stops the gradient."""
    coarse_samples: int = 64
    """Stratified samples per ray of the coarse network."""
    fine_samples: int = 128
    """Importance samples per ray added for the fine network (it sees coarse + fine)."""
    clip_to_bounds: bool = True
    """Also clip [near, far] to the scene box; the official code samples [near, far] only,
    which wastes samples when the data's near/far are loose."""
    rays_per_step: int = 1024
    """Rays per training step."""
    lr: float = 5e-4
    """Adam learning rate of both networks."""
    lr_decay_factor: float = 0.1
    """The learning rate is multiplied by this factor every lr_decay_steps (smoothly)."""
    lr_decay_steps: int = 250_000
    """NeRF's exponential decay: lr * lr_decay_factor ** (step / lr_decay_steps)."""

    flag_rules: ClassVar = {
        "depth": at_least(1),
        "width": at_least(1),
        "skip_layer": NON_NEGATIVE,
        "xyz_frequencies": NON_NEGATIVE,
        "dir_frequencies": NON_NEGATIVE,
        "coarse_samples": at_least(1),
        "fine_samples": NON_NEGATIVE,
        "rays_per_step": at_least(1),
        "lr": POSITIVE,
        "lr_decay_factor": POSITIVE,
        "lr_decay_steps": at_least(1),
    }


@dataclass
class GridFieldConfig:
    """A field made for a CPU (Instant-NGP's recipe, CPU kernels): multi-resolution dense feature
    grids, tiny MLPs, and samples marched only through the cells an occupancy grid marks."""

    levels: int = 8
    """Grid levels, resolutions spaced geometrically from min_resolution to max_resolution."""
    min_resolution: int = 16
    """Vertices per side of the coarsest grid."""
    max_resolution: int = 128
    """Vertices per side of the finest grid (memory grows with its cube: 128 -> 17 MB at 2 features)."""
    features_per_level: int = 2
    """Feature channels stored per grid vertex."""
    hidden_width: int = 64
    """Width of the density and colour MLPs (one hidden layer each, as small as Instant-NGP's)."""
    geo_features: int = 15
    """Features passed from the density MLP to the colour MLP."""
    dir_frequencies: int = 4
    """Positional-encoding frequencies of the viewing direction."""
    color_activation: ColorActivation = "sigmoid"
    """A sample's LDR colour from the colour MLP: sigmoid stops at 1, as the official MLP does;
    softplus is unbounded above, as 3DGS's SH colours are, so a sample seen through a clipped pixel
    can pass 1. What each costs and gains: docs/nerf_profile.md, "Clipped lights" (l2h_input = raw
    reaches the HDR gain without touching the LDR branch)."""
    # checkpoints written before this field existed trained L2H-CC on the colour
    l2h_input: L2hInput = dataclasses.field(default="raw", metadata={ABSENT_IN_SAVED_CONFIG: "activated"})
    """What L2H-CC reads per sample: raw, the colour before color_activation (the sigmoid's
    logit), or activated, the LDR colour itself (the paper's NeRF). The two carry the same
    information, but where the LDR loss holds samples near 1 (a clipped light, a clipped wall)
    the sigmoid's gradient vanishes, so the HDR loss cannot lift a light above the wall through
    it; through the logit it can. Measured on the built-in scenes: docs/nerf_profile.md, "L2H-CC on
    the logit"."""
    l2h_input_bound: float = dataclasses.field(default=12.0, metadata={ABSENT_IN_SAVED_CONFIG: 0.0})
    """In an unbounded scene (the contraction on) with l2h_input = raw: L2H-CC reads bound *
    tanh(logit / bound), the logit itself up to a few units and never beyond the bound (0: the
    logit as it is, as in bounded scenes). A sigmoid of 12 is 1 - 6e-6, so a logit beyond it is
    invisible in LDR; unbounded, a floater whose logit drifted to 200 was lifted to 1000x the sun
    and became the divisor of L_hdr's own-max normalisation. Bounded scenes keep the logit: the
    demo's bulb is drawn by red logits of 22-33, and bounded at 12 its HDR peak fell from 0.85 to 0.28
    of the truth (docs/outdoor.md, "NeRF: the brightest pixel in every batch, a bounded logit")."""
    density_activation: DensityActivation = "softplus"
    """softplus keeps gradients alive in empty space; relu is also accepted."""
    density_scale: float = 32.0
    """Density = scale * activation(raw + bias): a raw output of a few units then makes a voxel
    of the finest grid opaque, so surfaces sharpen in tens of steps, not thousands."""
    density_bias: float = -4.0
    """Starts the field nearly empty (scale * softplus(bias) ~ 0.6 per normalised unit)."""
    min_step: float = 1.0 / 128.0
    """Closest spacing of samples along a ray, in units of the box's half side (the box's longest
    side spans 2)."""
    max_samples_per_ray: int = 64
    """Most samples per ray: a ray spreads them over its occupied length, so early in training
    (everything occupied) a ray costs this many and later only ~occupied length / min_step."""
    importance_samples: int = 8
    """Samples per ray the field runs on with gradients (and the converters on), drawn from the
    marched samples' weights of a density pass without gradients; 0: every marched sample in
    front of early_stop_transmittance instead."""
    proposal: Literal["field", "cache"] = "field"
    """Weights the importance samples are drawn from: the field's density at the marched samples
    (a pass without gradients), or the occupancy grid's cached density (no network at all)."""
    early_stop_transmittance: float = 1e-4
    """While training, samples behind this transmittance (from a first, gradient-free density pass)
    are not evaluated again; when rendering they get no colour."""
    min_sample_weight: float = 1e-4
    """Samples whose rendering weight is below this get no colour: they cost the colour MLP and
    the per-sample HDR lifting (L2H-CC) but change a pixel by < this x value."""
    occupancy_resolution: int = 64
    """Cells per side of the occupancy grid."""
    occupancy_update_every: int = 16
    """Steps between occupancy-grid refreshes (from step 0)."""
    occupancy_decay: float = 0.95
    """A cell keeps max(decay * old, new) density: fading memory that never forgets a surface at once."""
    occupancy_threshold: float = 0.01
    """A cell is occupied when its opacity over one min_step reaches this (or the mean opacity of
    all seen cells, if that is lower: the untrained field is not all empty)."""
    occupancy_warmup_steps: int = 256
    """Refreshes evaluate every cell until this step, then a random quarter plus the occupied ones."""
    rays_per_step: int = 1024
    """Rays of the first training step; later steps take as many rays as samples_per_step allows."""
    samples_per_step: int = 32768
    """Samples a training step aims to carry gradients for (Instant-NGP's constant sample budget):
    few rays while samples still fill the box, up to max_rays_per_step once they crowd at surfaces."""
    max_rays_per_step: int = 16384
    """Most rays per training step."""
    grid_lr: float = 1e-2
    """Adam learning rate of the grid features."""
    mlp_lr: float = 1e-2
    """Adam learning rate of the tiny MLPs."""
    lr_final_factor: float = 0.1
    """Learning rates decay exponentially to this factor at the last step of the run."""
    far_samples: int = 32
    """With the contraction on: candidate samples per ray beyond the unit region, linear in
    disparity out to NerfConfig.far_distance; the occupancy grid keeps those in occupied cells."""

    flag_rules: ClassVar = {
        "levels": at_least(1),
        "min_resolution": at_least(2),
        "max_resolution": at_least(2),
        "features_per_level": at_least(1),
        "hidden_width": at_least(1),
        "geo_features": NON_NEGATIVE,
        "dir_frequencies": NON_NEGATIVE,
        "density_scale": POSITIVE,
        "density_bias": ANY_FINITE,
        "min_step": POSITIVE,
        "max_samples_per_ray": at_least(1),
        "importance_samples": NON_NEGATIVE,
        "early_stop_transmittance": FRACTION,
        "min_sample_weight": NON_NEGATIVE,
        "l2h_input_bound": NON_NEGATIVE,
        "occupancy_resolution": at_least(1),
        "occupancy_update_every": at_least(1),
        "occupancy_decay": between(0, 1, low_open=True),
        "occupancy_threshold": between(0, 1, high_open=True),
        "occupancy_warmup_steps": NON_NEGATIVE,
        "rays_per_step": at_least(1),
        "samples_per_step": at_least(1),
        "max_rays_per_step": at_least(1),
        "grid_lr": POSITIVE,
        "mlp_lr": POSITIVE,
        "lr_final_factor": POSITIVE,
        "far_samples": at_least(1),
    }


FieldConfig = GridFieldConfig | MlpFieldConfig


@dataclass
class NerfConfig:
    """NeRF backbone: the volume renderer plus a field (chosen by `--preset`: cpu or paper)."""

    field: Annotated[FieldConfig, tyro.conf.AvoidSubcommands] = dataclasses.field(default_factory=GridFieldConfig)
    """The radiance field and its sampling and optimiser settings: GridFieldConfig (preset cpu) or
    MlpFieldConfig (preset paper, the official 8 x 256 MLP)."""
    background_color: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour behind the scene, added as (1 - accumulation) * background_color to every group of 3
    composited channels (LDR and HDR alike); black, as in the paper's synthetic scenes. Unused
    where an environment map (background = environment) fills what the field leaves."""
    background: Literal["auto", "environment", "none"] = "auto"
    """What lies behind the field's last sample: environment, a learned map of raw colours by
    direction (core/environment.py) as one final sample per ray with the transmittance left
    (lifted to HDR like every sample); none, background_color. auto: environment iff the
    scene is unbounded (its data says so). The paper field has none (auto picks none for it)."""
    # checkpoints written before this field existed were never contracted
    contraction: Literal["auto", "on", "off"] = dataclasses.field(
        default="auto", metadata={ABSENT_IN_SAVED_CONFIG: "off"}
    )
    """on: nerfacto's scene contraction, so the grid field and the occupancy grid cover all of
    space (the scene box's unit region as it is, the rest squeezed into a shell around it) and
    samples beyond the box run linear in disparity out to far_distance. auto: on iff the scene
    is unbounded. The paper field is never contracted (auto picks off for it)."""
    far_distance: float = 1000.0
    """With the contraction on: where sampling ends, in half sides of the scene box from its centre."""
    environment_width: int = 512
    """Texels around the environment map's equator (finest level)."""
    render_chunk: int = 8192
    """Rays rendered at once when a whole image is rendered in pieces: memory is bounded by
    render_chunk x the field's samples per ray."""

    flag_rules: ClassVar = {
        "background_color": FRACTION,
        "far_distance": between(1, 1e8, low_open=True),
        "environment_width": at_least(16),
        "render_chunk": at_least(1),
    }

    def __post_init__(self):
        # Configs saved before the environment background held the colour in `background`.
        if isinstance(self.background, (tuple, list)):
            self.background_color, self.background = tuple(self.background), "none"
