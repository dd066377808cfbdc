"""Where a run's data comes from, and which exposures it trains and tests on."""

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

from mono_hdr_plugin.core.metrics import SSIM_WINDOW
from mono_hdr_plugin.core.validation import MAX_IMAGE_SIDE, POSITIVE, SEED, between

TRAINING_RESOLUTION = between(SSIM_WINDOW, MAX_IMAGE_SIDE)
"""--resolution of a studio scene that is trained or scored: SSIM's window at least, the studio's largest."""


@dataclass
class DataConfig:
    """Dataset selection shared by every command that reads a scene."""

    data: Path | None = None
    """A dataset folder on disk (HDR-GS, HDR-NeRF synthetic/real, LLFF or nerfstudio layout, detected)."""
    scene: str | None = None
    """A built-in studio scene (see `mono-hdr scenes`), instead of --data."""
    layout: str = "auto"
    """On-disk layout of --data: auto detects it from the files present; or a registered layout
    (`mono-hdr layouts`: llff, hdr-gs, hdr-nerf-synthetic, hdr-nerf-real, nerfstudio, or a plugin's)."""
    protocol: Literal["single", "multi", "fixed"] = "single"
    """single: the paper's setting, every view at exposure t1/t3/t5 chosen by --exposure-index
    (train and LDR test); multi: HDR-NeRF/HDR-GS, each train view one random exposure of
    t1/t3/t5, test views at all five; fixed: every view at --fixed-exposure seconds."""
    exposure_index: int = 1
    """0, 1, 2 select t1, t3, t5 in the single-exposure protocol."""
    fixed_exposure: float | None = None
    """Exposure in seconds for the fixed protocol (must be one the data has)."""
    resolution: int | None = None
    """--scene only: render and photograph the studio scene at N x N pixels (default: its own 128;
    each size is rendered once and cached). A --data folder keeps its size: shrink it with --downscale."""
    downscale: int = 1
    """Integer factor to shrink images by (area averaging; cameras' focal lengths and principal point
    scale with them), 2 reproduces the paper's half_res. An LLFF scene's images_N/ is read for N."""
    exposure_seed: int = 0
    """Seed of the multi protocol's random exposure choice and of the studio's sensor noise."""
    extent: Literal["auto", "bounded", "unbounded"] = "auto"
    """Whether the scene reaches to infinity (an open sky: the backbones' `auto` settings add an
    environment behind the scene, NeRF contracts space). auto: a studio scene's content says; a
    --data folder is decided from its training photos, whatever its metadata claims (docs/outdoor.md,
    "When a scene counts as unbounded"); bounded / unbounded force it."""

    flag_rules: ClassVar = {
        "exposure_index": between(0, 2),
        "fixed_exposure": POSITIVE,
        "resolution": TRAINING_RESOLUTION,
        "downscale": POSITIVE,
        "exposure_seed": SEED,
    }
