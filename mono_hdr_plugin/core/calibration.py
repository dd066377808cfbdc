"""The absolute level of a model's HDR: one radiance scale, fitted on the training views.

Mono-HDR's L_hdr compares images each divided by its own maximum, so nothing in training fixes
the HDR's absolute level and it drifts (docs/method.md, "Calibrated HDR"). A trained model is
therefore given a radiance scale s, and every HDR output is s x the method's HDR. s is fitted on
pixels the training photos expose well (neither clipped nor lost in noise), in one of two units:

- ground_truth: the training views' HDR ground truth, where there is some: s = median(gt / hdr).
- exposure_seconds: radiance such that radiance x t through the camera response gives the photo,
  as a bracket merge defines it: s = median(f^-1(photo) / (t x hdr)). When the capture knows no
  exposure times (reference_exposure), t is relative to the reference view's exposure.

One global scale, not one per channel: a per-channel fit would also repaint the model's colour
errors with the training views' white balance, and the scores would no longer show them.
The median of the log ratios is the estimator: a few pixels (a light the model misses, a
specular highlight that moved) cannot drag it, as they would a least-squares fit.
"""

import math
from dataclasses import asdict, dataclass
from typing import Literal, get_args

import numpy as np
import torch
from torch import Tensor

WELL_EXPOSED = (0.05, 0.95)
"""A photo's code values in this range are neither clipped nor lost in noise."""
MIN_SAMPLES = 64
"""Fewer well-exposed samples than this: the fit falls back to every lit sample."""

Units = Literal["uncalibrated", "ground_truth", "exposure_seconds", "reference_exposure"]
UNITS: tuple[str, ...] = get_args(Units)
UNIT_TEXT = {
    "uncalibrated": "the method's own scale (no calibration was fitted)",
    "ground_truth": "the training views' HDR ground truth",
    "exposure_seconds": "linear photo value per second of exposure (through the camera response)",
    "reference_exposure": "linear photo value at the reference view's exposure (the capture knows no times)",
}


@dataclass(frozen=True)
class RadianceCalibration:
    """calibrated HDR = scale x the method's HDR, in `units`; fitted on `samples` pixel values at
    training step `step`. `basis`: what ties the HDR to radiance in training ("12 HDR ground-truth
    views", "the sRGB response (no HDR views)", ...; training.hdr_prior.hdr_basis)."""

    scale: float = 1.0
    units: Units = "uncalibrated"
    samples: int = 0
    step: int | None = None
    basis: str = "unknown"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"a radiance scale must be a positive number, got {self.scale}")
        if self.units not in UNITS:
            raise ValueError(f"unknown radiance units {self.units!r}; one of {', '.join(UNITS)}")

    @property
    def fitted(self) -> bool:
        return self.units != "uncalibrated"

    def state(self) -> dict:
        """What a checkpoint holds (plain values: it loads with weights_only)."""
        return asdict(self)

    @classmethod
    def from_state(cls, state: dict) -> "RadianceCalibration":
        return cls(**state)

    def describe(self) -> str:
        return f"x{self.scale:.6g}, in units of {UNIT_TEXT[self.units]}"


def well_exposed(photo: Tensor) -> Tensor:
    """[...] True where every channel of the photo's code values [..., 3] lies inside WELL_EXPOSED."""
    return well_exposed_channels(photo).all(-1)


def well_exposed_channels(photo: Tensor) -> Tensor:
    """[..., 3] True where the photo's code value lies inside WELL_EXPOSED, channel by channel: a pixel
    whose red clips still records its green and blue."""
    low, high = WELL_EXPOSED
    return (photo > low) & (photo < high)


def median_log_ratio(target: Tensor, prediction: Tensor) -> tuple[float, int]:
    """exp(median(log target - log prediction)) over the entries where both are positive and finite,
    and how many entries that was (scale 1.0 over none)."""
    usable = (target > 0) & (prediction > 0) & torch.isfinite(target) & torch.isfinite(prediction)
    count = int(usable.sum())
    if count == 0:
        return 1.0, 0
    ratios = torch.log(target[usable].double()) - torch.log(prediction[usable].double())
    return math.exp(float(np.median(ratios.numpy()))), count  # numpy's median: the middle two averaged


def fit_scale(target: Tensor, prediction: Tensor, photo: Tensor) -> tuple[float, int]:
    """The scale s with target ~ s x prediction ([N, 3] each): the median log ratio over pixels the
    photo [N, 3] exposes well, over every pixel when fewer than MIN_SAMPLES of them are usable."""
    exposed = well_exposed(photo)
    scale, count = median_log_ratio(target[exposed], prediction[exposed])
    if count >= MIN_SAMPLES:
        return scale, count
    return median_log_ratio(target, prediction)
