"""A held-out view's appearance in evaluation: its exposure and white balance are unknown to a model
that learned them per training view, so they are fitted to the photo.

Two fits, two scores:
- as given: a view of unknown exposure is brightened by the one exposure that best matches its whole
  photo (`ldr_psnr`, `ldr_ssim`; a view of known exposure is rendered at it);
- appearance fitted (NeRF-W's protocol): exposure and three white balance gains are fitted on the
  LEFT half of the photo and the render scored on the RIGHT half only, so the fit cannot absorb the
  errors it is scored on (`ldr_psnr_appearance_fitted`, `ldr_ssim_appearance_fitted`).

Both fits brighten the canonical render, the one at the reference view's exposure and the mean white
balance, through the camera response (core.exposure); for the methods that take exposure this
treats their render at the reference exposure as that photo (docs/own_photos.md).
"""

import dataclasses
import math
from typing import Any

import torch
from torch import Tensor

from mono_hdr_plugin.core.exposure import brighten, fit_log_relative, fit_log_scales, reference_view
from mono_hdr_plugin.core.metrics import SSIM_RADIUS, psnr, ssim
from mono_hdr_plugin.core.white_balance import split_log_scales
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.pipeline import Frame, Pipeline

APPEARANCE_PROTOCOL = "left-half fit, right-half score"


def appearance_protocol_runs(pipeline: Pipeline, setting: str) -> bool:
    """--eval-appearance: on, off, or auto (on when the run learned exposure or white balance)."""
    if setting != "auto":
        return setting == "on"
    return pipeline.exposures is not None and pipeline.exposures.appearance_learned


def reference_exposure(pipeline: Pipeline, scene: SceneData) -> float:
    """Seconds of the canonical render: the reference view's exposure (core.exposure.reference_view)."""
    if pipeline.exposures is not None:
        return float(pipeline.exposures.reference_exposure)
    return scene.train[reference_view(scene.train)].exposure


def match_exposure(reference: Frame, image: Tensor, response: Tensor) -> Frame:
    """The canonical `reference` render brightened by the one exposure that best matches `image`."""
    log_relative = fit_log_relative(reference.ldr, image, response)
    return dataclasses.replace(reference, ldr=brighten(reference.ldr, log_relative, response))


def appearance_fitted_scores(reference: Frame, image: Tensor, response: Tensor) -> dict[str, Any]:
    """LDR PSNR / SSIM on the right half of `image` [H, W, 3] of the canonical `reference` render,
    with exposure and white balance fitted on its left half; the fitted values with them."""
    middle = image.shape[1] // 2
    left, right = slice(None, middle), slice(middle, None)
    log_scales = fit_log_scales(reference.ldr[:, left], image[:, left], response)
    ldr = brighten(reference.ldr[:, right], log_scales, response)
    log_exposure, gains = split_log_scales(log_scales)
    return {
        "ldr_psnr_appearance_fitted": psnr(ldr, image[:, right]),
        "ldr_ssim_appearance_fitted": _ssim(ldr, image[:, right]),
        "appearance_fitted_exposure": float(torch.exp(log_exposure)),
        "appearance_fitted_gains": gains.tolist(),
    }


def _ssim(ldr: Tensor, photo: Tensor) -> float:
    """SSIM of a half image; NaN (left out of the mean) where it is narrower than SSIM's window."""
    if min(photo.shape[:2]) < 2 * SSIM_RADIUS + 1:
        return math.nan
    return ssim(ldr.double(), photo.double()).item()
