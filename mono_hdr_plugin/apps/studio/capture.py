"""Capture simulator: HDR radiance -> one LDR photo, applying only the effects a scene declares.

The stages follow the imaging equation I_l = CRF(clip(dt / g * I_h + I_0 + eps)) (Hasinoff et
al. 2010, docs/method.md) in physical order:

    exposure -> gain -> offset -> noise -> vignette -> white_balance -> crf -> clip -> quantize

Each stage is a small function of (image, settings, context); `capture` runs exactly the
stages named in `effects` and never calls the others, so an undeclared effect changes
nothing and costs nothing. Stages with a physical inverse have one (`invert_*`).
"""

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from mono_hdr_plugin.core.colour import RESPONSE_CURVES, ResponseCurve, decode_curve, encode_curve

PHYSICAL_ORDER = ("exposure", "gain", "offset", "noise", "vignette", "white_balance", "crf", "clip", "quantize")
QUANTIZE_BITS = (8, 10, 12, 16)
CRF_NAMES = (*RESPONSE_CURVES, "gamma", "film")


@dataclass(frozen=True)
class CaptureSettings:
    """Camera parameters; a stage reads only its own fields."""

    gain: float = 1.0
    """Sensor gain (ISO): multiplies the exposed signal."""
    offset: float = 0.0
    """Black level added by the sensor, in units of the saturation level."""
    full_well: float = 2000.0
    """Electrons at saturation: the Poisson (shot) noise scale."""
    read_noise: float = 0.002
    """Standard deviation of the Gaussian read noise, in units of the saturation level."""
    vignette: float = 0.3
    """Relative brightness loss at the image corners (0 = none)."""
    white_balance: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Per-channel gains applied before the response curve."""
    crf: str = "srgb"
    """Camera response curve: srgb or bt709 (colour-science), gamma, or film (sigmoid)."""
    gamma: float = 2.2
    """Exponent of the gamma response curve."""
    film_contrast: float = 1.6
    """Slope of the film curve in log exposure (higher is more contrasty)."""
    film_shoulder: float = 0.25
    """Shoulder of the film curve: the curve tends to 1 + shoulder for very bright inputs."""
    saturation: float = 1.0
    """Clipping level after the response curve."""
    bits: int = 8
    """Quantisation bit depth: 8, 10, 12 or 16."""

    def __post_init__(self):
        if self.bits not in QUANTIZE_BITS:
            raise ValueError(f"bits must be one of {QUANTIZE_BITS}, got {self.bits}")
        if self.crf not in CRF_NAMES:
            raise ValueError(f"crf must be one of {CRF_NAMES}, got {self.crf!r}")
        if not (self.gain > 0 and self.full_well > 0 and self.gamma > 0 and self.saturation > 0):
            raise ValueError("gain, full_well, gamma and saturation must be positive")
        if not 0 <= self.vignette < 1:
            raise ValueError(f"vignette must be in [0, 1), got {self.vignette}")


@dataclass(frozen=True)
class CaptureContext:
    """Per-photo values: exposure time and the seed of this photo's noise."""

    exposure: float
    seed: int = 0
    extra: dict = field(default_factory=dict)


def apply_exposure(image: np.ndarray, settings: CaptureSettings, context: CaptureContext):
    """Radiance times exposure time: the energy collected per pixel."""
    return image * np.float32(context.exposure)


def invert_exposure(image, settings, context):
    return image / np.float32(context.exposure)


def apply_gain(image, settings: CaptureSettings, context):
    """Analogue gain (ISO)."""
    return image * np.float32(settings.gain)


def invert_gain(image, settings, context):
    return image / np.float32(settings.gain)


def apply_offset(image, settings: CaptureSettings, context):
    """Sensor black level I_0."""
    return image + np.float32(settings.offset)


def invert_offset(image, settings, context):
    return image - np.float32(settings.offset)


def apply_noise(image, settings: CaptureSettings, context: CaptureContext):
    """Poisson shot noise on the collected electrons plus Gaussian read noise, seeded per photo."""
    rng = np.random.default_rng(context.seed)
    electrons = rng.poisson(np.clip(image, 0, None).astype(np.float64) * settings.full_well)
    signal = electrons / settings.full_well + rng.normal(0.0, settings.read_noise, image.shape)
    return signal.astype(np.float32)


def vignette_falloff(height: int, width: int, strength: float) -> np.ndarray:
    """[H, W, 1] multiplicative falloff: 1 at the centre, 1 - strength at the corners."""
    ys = (np.arange(height) + 0.5) / height * 2 - 1
    xs = (np.arange(width) + 0.5) / width * 2 - 1
    radius2 = (xs[None, :] ** 2 + ys[:, None] ** 2) / 2
    return (1.0 - strength * radius2).astype(np.float32)[..., None]


def apply_vignette(image, settings: CaptureSettings, context):
    """Lens vignetting: darker towards the corners."""
    height, width = image.shape[:2]
    return image * vignette_falloff(height, width, settings.vignette)


def invert_vignette(image, settings, context):
    height, width = image.shape[:2]
    return image / vignette_falloff(height, width, settings.vignette)


def apply_white_balance(image, settings: CaptureSettings, context):
    """Per-channel white-balance gains."""
    return image * np.asarray(settings.white_balance, np.float32)


def invert_white_balance(image, settings, context):
    return image / np.asarray(settings.white_balance, np.float32)


def response_curve(x: np.ndarray, settings: CaptureSettings) -> np.ndarray:
    """Camera response curve (linear -> encoded); monotonic, CRF(0) = 0, CRF(1) = 1.

    Negative inputs (noise below the black level) read as 0: a pixel cannot report less
    than no light.
    """
    x = np.clip(x, 0, None)
    if settings.crf in RESPONSE_CURVES:
        return encode_curve(x, cast(ResponseCurve, settings.crf)).astype(np.float32)
    if settings.crf == "gamma":
        return (x ** (1.0 / settings.gamma)).astype(np.float32)
    # Film: a sigmoid in log exposure, (1 + k) x^n / (x^n + k), scaled so that film(1) = 1.
    n, k = settings.film_contrast, settings.film_shoulder
    power = x.astype(np.float64) ** n
    return ((1 + k) * power / (power + k)).astype(np.float32)


def inverse_response_curve(y: np.ndarray, settings: CaptureSettings) -> np.ndarray:
    """Inverse of `response_curve` on its range."""
    y = np.clip(y, 0, None)
    if settings.crf in RESPONSE_CURVES:
        return decode_curve(y, cast(ResponseCurve, settings.crf)).astype(np.float32)
    if settings.crf == "gamma":
        return (y**settings.gamma).astype(np.float32)
    n, k = settings.film_contrast, settings.film_shoulder
    y = np.minimum(y.astype(np.float64), (1 + k) * (1 - 1e-12))  # the film curve tends to 1 + k
    return ((k * y / (1 + k - y)) ** (1.0 / n)).astype(np.float32)


def apply_crf(image, settings: CaptureSettings, context):
    """The camera response curve."""
    return response_curve(image, settings)


def invert_crf(image, settings, context):
    return inverse_response_curve(image, settings)


def apply_clip(image, settings: CaptureSettings, context):
    """Saturation: nothing above the white level, nothing below zero."""
    return np.clip(image, 0.0, settings.saturation) / np.float32(settings.saturation)


def apply_quantize(image, settings: CaptureSettings, context):
    """Round to the levels of a `bits`-bit file."""
    levels = np.float32(2**settings.bits - 1)
    return np.round(np.clip(image, 0.0, 1.0) * levels) / levels


STAGES: dict[str, Callable] = {
    "exposure": apply_exposure,
    "gain": apply_gain,
    "offset": apply_offset,
    "noise": apply_noise,
    "vignette": apply_vignette,
    "white_balance": apply_white_balance,
    "crf": apply_crf,
    "clip": apply_clip,
    "quantize": apply_quantize,
}
INVERSES: dict[str, Callable] = {
    "exposure": invert_exposure,
    "gain": invert_gain,
    "offset": invert_offset,
    "vignette": invert_vignette,
    "white_balance": invert_white_balance,
    "crf": invert_crf,
}


def validate_effects(effects: tuple[str, ...]) -> tuple[str, ...]:
    """Check effect names; returns them in physical order."""
    unknown = set(effects) - set(PHYSICAL_ORDER)
    if unknown:
        raise ValueError(f"unknown capture effect(s) {sorted(unknown)}; choose from {PHYSICAL_ORDER}")
    return tuple(name for name in PHYSICAL_ORDER if name in effects)


def capture(
    hdr: np.ndarray,
    exposure: float,
    effects: tuple[str, ...],
    settings: CaptureSettings = CaptureSettings(),
    seed: int = 0,
) -> np.ndarray:
    """One simulated photo [H, W, 3] float32 of linear radiance `hdr` at `exposure` seconds.

    Applies exactly the declared `effects`, in physical order.
    """
    context = CaptureContext(exposure=exposure, seed=seed)
    image = np.asarray(hdr, np.float32)
    for name in validate_effects(effects):
        image = STAGES[name](image, settings, context)
    return image


def linearise(
    ldr: np.ndarray, exposure: float, effects: tuple[str, ...], settings: CaptureSettings = CaptureSettings()
) -> np.ndarray:
    """Undo the invertible stages of `capture` (noise, clipping and rounding stay)."""
    context = CaptureContext(exposure=exposure)
    image = np.asarray(ldr, np.float32)
    for name in reversed(validate_effects(effects)):
        if name in INVERSES:
            image = INVERSES[name](image, settings, context)
    return image
