"""Hyper-parameters of the NeRF backbone: one dataclass per field, one on top choosing.

Every field is a tyro flag (`--field`, `--paper.coarse-samples`, `--fast.max-resolution`, ...).
Each field config carries its own sampling and optimiser settings, so `--field paper` alone
already gives the official recipe and `--field fast` the CPU one: the presets are the two
values of `field`.
"""

import dataclasses
from dataclasses import dataclass
from typing import ClassVar, Literal

from mono_hdr_plugin.validation import ANY_FINITE, FRACTION, NON_NEGATIVE, POSITIVE, at_least, between

DensityActivation = Literal["relu", "softplus"]


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

    flag_rules: ClassVar = {"depth": at_least(1), "width": at_least(1), "skip_layer": NON_NEGATIVE,
                            "xyz_frequencies": NON_NEGATIVE, "dir_frequencies": NON_NEGATIVE,
                            "coarse_samples": at_least(1), "fine_samples": NON_NEGATIVE, "rays_per_step": at_least(1),
                            "lr": POSITIVE, "lr_decay_factor": POSITIVE, "lr_decay_steps": at_least(1)}


@dataclass
class GridFieldConfig:
    """A CPU-friendly field: multi-resolution dense grids + tiny MLPs, sampled through a
    density grid that doubles as occupancy grid (skip empty space) and proposal (importance
    samples where the cached density says the surface is)."""

    levels: int = 4
    """Grid levels, resolutions spaced geometrically from min_resolution to max_resolution."""
    min_resolution: int = 16
    """Vertices per side of the coarsest grid."""
    max_resolution: int = 96
    """Vertices per side of the finest grid (memory grows with its cube)."""
    features_per_level: int = 2
    """Feature channels stored per grid vertex."""
    hidden_width: int = 64
    """Width of the density and colour MLPs (one hidden layer each, as small as Instant-NGP's)."""
    geo_features: int = 15
    """Features passed from the density MLP to the colour MLP."""
    dir_frequencies: int = 4
    """Positional-encoding frequencies of the viewing direction."""
    density_activation: DensityActivation = "softplus"
    """softplus keeps gradients alive in empty space; relu is also accepted."""
    density_scale: float = 32.0
    """Density = scale * activation(raw + bias): a raw output of a few units then makes a voxel
    of the finest grid opaque, so surfaces sharpen in tens of steps, not thousands."""
    density_bias: float = -4.0
    """Starts the field nearly empty (scale * softplus(bias) ~ 0.6 per normalised unit)."""
    uniform_samples: int = 32
    """Stratified samples per ray over the ray's segment inside the scene box."""
    importance_samples: int = 32
    """Samples per ray drawn from the density grid's volume-rendering weights."""
    proposal_samples: int = 128
    """Density-grid look-ups per ray that build the importance pdf (cheap, no network)."""
    density_grid_resolution: int = 64
    """Cells per side of the density grid."""
    density_grid_update_every: int = 16
    """Steps between density-grid refreshes (each evaluates the field once per cell)."""
    density_grid_decay: float = 0.95
    """A cell keeps max(decay * old, new): fading memory that never forgets a surface at once."""
    occupancy_threshold: float = 0.01
    """Samples where the cached density (per unit of the normalised box) is below this are
    skipped once the grid has been filled."""
    min_sample_weight: float = 1e-4
    """Samples whose rendering weight is below this are dropped before colour: they cost the
    colour MLP and the per-sample HDR lifting (L2H-CC) but change a pixel by < this x value."""
    rays_per_step: int = 1024
    """Rays per training step."""
    grid_lr: float = 1e-2
    """Adam learning rate of the grid features."""
    mlp_lr: float = 1e-2
    """Adam learning rate of the tiny MLPs."""
    lr_final_factor: float = 0.1
    """Learning rates decay exponentially to this factor at the last step of the run."""

    flag_rules: ClassVar = {
        "levels": at_least(1), "min_resolution": at_least(2), "max_resolution": at_least(2),
        "features_per_level": at_least(1), "hidden_width": at_least(1), "geo_features": NON_NEGATIVE,
        "dir_frequencies": NON_NEGATIVE, "density_scale": POSITIVE, "density_bias": ANY_FINITE,
        "uniform_samples": at_least(1), "importance_samples": NON_NEGATIVE, "proposal_samples": at_least(1),
        "density_grid_resolution": at_least(1), "density_grid_update_every": at_least(1),
        "density_grid_decay": between(0, 1, low_open=True), "occupancy_threshold": NON_NEGATIVE,
        "min_sample_weight": NON_NEGATIVE, "rays_per_step": at_least(1), "grid_lr": POSITIVE, "mlp_lr": POSITIVE,
        "lr_final_factor": POSITIVE}


@dataclass
class NerfConfig:
    """NeRF backbone: the volume renderer plus the field chosen by `field`."""

    field: Literal["paper", "fast"] = "fast"
    """paper: the official 8 x 256 MLP, 64 + 128 samples (faithful, ~40 s per step on 2 CPU cores);
    fast: multi-resolution grids + tiny MLPs with density-grid sampling (CPU default)."""
    paper: MlpFieldConfig = dataclasses.field(default_factory=MlpFieldConfig)
    """Settings used when field=paper."""
    fast: GridFieldConfig = dataclasses.field(default_factory=GridFieldConfig)
    """Settings used when field=fast."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Colour behind the scene, added as (1 - accumulation) * background to every group of 3
    composited channels (LDR and HDR alike); black, as in the paper's synthetic scenes."""
    render_chunk: int = 8192
    """Rays rendered at once when a whole image is rendered in pieces (memory bound)."""

    flag_rules: ClassVar = {"background": FRACTION, "render_chunk": at_least(1)}
