"""The settings of one training run (`mono-hdr train <backbone> --help`) and the checks made
before any data is read."""

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, ClassVar

import tyro

from mono_hdr_plugin.core.camera_optimizer import CameraOptConfig
from mono_hdr_plugin.core.configs import ABSENT_IN_SAVED_CONFIG, config_from_dict
from mono_hdr_plugin.core.exposure import ExposureConfig
from mono_hdr_plugin.core.validation import (
    MAX_IMAGE_SIDE,
    NON_NEGATIVE,
    POSITIVE,
    SEED,
    FlagError,
    at_least,
    between,
    check_flags,
)
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.layouts import LAYOUTS
from mono_hdr_plugin.methods.base import METHODS, MethodConfig, method_config_for
from mono_hdr_plugin.training.regions import MIN_REGION_PIXELS

TRAIN_OUTPUTS = ("checkpoints", "renders", "metrics.json", "viewer", "refined_poses.json")
"""What `mono-hdr train` writes in --out; --overwrite removes exactly these."""


@dataclass
class TrainConfig:
    """Train one backbone with one method; the backbone's own options follow."""

    backbone: Any
    data: Annotated[DataConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=DataConfig)
    hdr: Annotated[MethodConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=MethodConfig)
    exposure: Annotated[ExposureConfig, tyro.conf.OmitArgPrefixes] = field(default_factory=ExposureConfig)
    camera: Annotated[CameraOptConfig, tyro.conf.OmitArgPrefixes] = field(
        default_factory=CameraOptConfig,
        metadata={ABSENT_IN_SAVED_CONFIG: CameraOptConfig(camera_opt="off")},  # runs before it refined nothing
    )
    preset: str | None = None
    """Start from a named preset of the backbone (listed by `mono-hdr backbones`; default: its
    first); other flags override it."""
    max_steps: int | None = None
    """Optimiser steps (default 3000; with --max-seconds alone, as many as fit in that time). With
    both flags the run ends at whichever comes first; schedules (learning-rate decay,
    densification) end with the run."""
    max_seconds: float | None = None
    """Stop after this many seconds of training (evaluation and checkpoints not counted). Without
    --max-steps the time alone ends the run. Schedules (learning-rate decay, densification) are
    sized to the steps that fit, re-estimated from the measured step time while training."""
    out: Path = Path("outputs/run")
    """Output folder: checkpoints/, renders/, metrics.json."""
    resume: bool = False
    """Continue the run in --out from OUT/checkpoints/latest.pt (same data, backbone and method)."""
    overwrite: bool = False
    """Replace the earlier run in --out (its checkpoints/, renders/ and metrics.json) instead of refusing."""
    seed: int = 0
    """Seed of initialisation and view order."""
    hdr_view_ratio: str = "1:1"
    """LDR:HDR training-view ratio: 1:1 every view has HDR ground truth, 2:1 half of them, 1:0
    none (LDR only), 0:1 HDR only (no LDR loss)."""
    eval_every: int = 0
    """Evaluate on the test views every N steps (0: only at the end)."""
    pyramid_levels: int | None = None
    """Coarse-to-fine training: levels of an image pyramid (1: off; 3: train on the views at 1/4, then 1/2
    a side, then full size). Cameras' intrinsics scale with the images; a 3DGS budget with the pixels.
    None: automatic. A backbone that renders whole images (3DGS's cpu preset) on views of 512 px a side or
    more gets as many levels as keep the coarsest at 128 px or more (3 at 512 px, where it gains 5 dB HDR
    in 10 minutes; at 256 px 2 levels did not pay, docs/sizes.md); smaller views, a backbone that trains
    on ray batches (NeRF), whose step costs the same at any size, and 3DGS's paper preset (the official
    recipe has no pyramid) get 1."""
    pyramid_share: float = 0.5
    """With --pyramid-levels above 1: the share of the run trained below full size, split evenly among
    the coarser levels, coarsest first."""
    region_pixels: int | None = None
    """Region training: a 3DGS step renders and scores a random crop of about this many pixels of its view
    instead of the whole image (about sqrt a side; a view, or pyramid level, with fewer pixels trains
    whole), so a step costs the same at any image size. None: whole images. Refused for a backbone that
    trains on ray batches (NeRF). Off by default: the curves measured so far favour whole images or the
    pyramid (docs/sizes.md, "Region training")."""
    checkpoint_every: int = 1000
    """Write OUT/checkpoints/latest.pt every N steps (and at the end)."""
    max_eval_views: int | None = None
    """Evaluate on at most this many test views (None: all)."""
    save_renders: bool = True
    """Write EXR (HDR) and PNG (LDR, tone-mapped HDR) renders of the test views at the end."""
    nan_patience: int = 20
    """Stop after this many consecutive steps with a non-finite loss or gradient."""
    quiet: bool = False
    """No progress bar (tests, benchmarks)."""
    viewer: bool = False
    """Watch training live in the browser (see `mono-hdr view --help`); it stays open after training."""
    viewer_port: int = 7007
    """Port of the --viewer (the next free one when taken)."""
    viewer_host: str = "127.0.0.1"
    """Address the --viewer listens on; anything but localhost opens it to the network."""

    flag_rules: ClassVar = {
        "max_steps": NON_NEGATIVE,
        "max_seconds": POSITIVE,
        "seed": SEED,
        "eval_every": NON_NEGATIVE,
        "checkpoint_every": at_least(1),
        "pyramid_levels": between(1, 6),
        "pyramid_share": between(0, 1, high_open=True),
        "region_pixels": between(MIN_REGION_PIXELS, MAX_IMAGE_SIDE**2),
        "max_eval_views": at_least(1),
        "nan_patience": at_least(1),
        "viewer_port": between(0, 65535),
    }


DEFAULT_MAX_STEPS = 3000


def step_limit(config: TrainConfig) -> int | None:
    """The step a run ends at: --max-steps; without it 3000, or none when --max-seconds alone
    bounds the run (a user who gives a time budget expects it to be used)."""
    if config.max_steps is not None:
        return config.max_steps
    return None if config.max_seconds is not None else DEFAULT_MAX_STEPS


def parse_view_ratio(ratio: str) -> tuple[int, int]:
    try:
        ldr, hdr = (int(part) for part in ratio.split(":"))
    except ValueError as error:
        raise ValueError(f"--hdr-view-ratio must look like 2:1 (LDR:HDR), got {ratio!r}") from error
    if ldr < 0 or hdr < 0 or ldr + hdr == 0:
        raise ValueError(f"--hdr-view-ratio needs non-negative parts, not both zero; got {ratio!r}")
    return ldr, hdr


def check_train_config(config: TrainConfig) -> None:
    """Refuse flags that cannot work before any work is done, naming the flag: every numeric flag
    (run, data, method and backbone alike) against its rule (validation.py), then the rest."""
    check_flags(config)
    if config.resume and config.overwrite:
        raise FlagError("--resume continues the run in --out and --overwrite replaces it: pass one of them")
    parse_view_ratio(config.hdr_view_ratio)
    METHODS.get(config.hdr.method)  # a misspelt method or layout is named before any data is read
    if config.data.layout != "auto":
        LAYOUTS.get(config.data.layout)


def hdr_supervised_views(num_views: int, ratio: str) -> list[bool]:
    """Which training views keep their HDR ground truth, spread evenly, for an LDR:HDR ratio."""
    ldr, hdr = parse_view_ratio(ratio)
    if hdr == 0:
        return [False] * num_views
    fraction = 1.0 if ldr <= hdr else hdr / ldr
    count = max(1, math.ceil(fraction * num_views))
    chosen = {int(i * num_views / count) for i in range(count)}
    return [i in chosen for i in range(num_views)]


_TRAIN_CONFIGS: dict[tuple[type, type], type] = {}


def train_config_for(backbone_config_class: type, method: str | None = None) -> type:
    """A TrainConfig subclass whose `backbone` field has the backbone's own config type and whose
    `hdr` field is the method's (`method_config_for`: its own flags; None: the default method)."""
    method_config_class = method_config_for(MethodConfig.method if method is None else method)
    key = (backbone_config_class, method_config_class)
    if key not in _TRAIN_CONFIGS:
        _TRAIN_CONFIGS[key] = dataclass(
            type(
                f"Train{backbone_config_class.__name__}",
                (TrainConfig,),
                {
                    "__annotations__": {
                        "backbone": backbone_config_class,
                        "hdr": Annotated[method_config_class, tyro.conf.OmitArgPrefixes],
                    },
                    "backbone": field(default_factory=backbone_config_class),
                    "hdr": field(default_factory=method_config_class),
                    "__doc__": TrainConfig.__doc__,
                },
            )
        )
    return _TRAIN_CONFIGS[key]


def saved_train_config(backbone_config_class: type, values: dict) -> TrainConfig:
    """A run config saved by `config_to_json`, rebuilt with its backbone's and its method's types
    (a config saved before methods had options of their own included)."""
    return config_from_dict(train_config_for(backbone_config_class, values["hdr"]["method"]), values)
