"""A held-out view's appearance in evaluation: its exposure and white balance are unknown to a model
that learned them per training view, so they are fitted to the photo.

Two fits, two scores:
- as given: a view of unknown exposure is brightened by the one exposure that best matches its whole
  photo (`ldr_psnr`, `ldr_ssim`; a view of known exposure is rendered at it);
- appearance fitted (NeRF-W's protocol): exposure and three white balance gains are fitted on the
  LEFT half of the photo and the render scored on the RIGHT half only, so the fit cannot absorb the
  errors it is scored on (`ldr_psnr_appearance_fitted`, `ldr_ssim_appearance_fitted`). Where training
  refined its poses, the held-out view's pose is fitted on the left half too (BARF's protocol,
  `fit_held_out_pose`): refinement moves the model's world a little, and a held-out pose given in the
  old one no longer matches it.

Both fits brighten the canonical render, the one at the reference view's exposure and the mean white
balance, through the camera response (core.exposure); for the methods that take exposure this
treats their render at the reference exposure as that photo (docs/own_photos.md).
"""

import dataclasses
import math
from typing import Any

import torch
from torch import Tensor

from mono_hdr_plugin.core.camera_optimizer import PoseCorrections, rotation_angle_degrees
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.exposure import brighten, fit_log_relative, fit_log_scales, reference_view
from mono_hdr_plugin.core.metrics import SSIM_WINDOW, psnr, ssim
from mono_hdr_plugin.core.white_balance import split_log_scales
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.pipeline import Frame, Pipeline

APPEARANCE_PROTOCOL = "left-half fit, right-half score"
POSE_FIT_STEPS = 100
POSE_FIT_LR = (3e-3, 1e-4)
"""Adam's learning rate of the held-out pose fit, first and last step (radians, scene radii)."""
POSE_FIT_RAYS = 4096
"""Rays a step of the pose fit renders where the backbone renders pixel batches (NeRF); 3DGS renders
the whole image and scores its left half."""


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
    if min(photo.shape[:2]) < SSIM_WINDOW:
        return math.nan
    return ssim(ldr.double(), photo.double()).item()


def nearest_training_view(scene: SceneData, camera: Camera) -> int:
    """Index of the training view whose camera centre is nearest `camera`'s."""
    centres = torch.stack([view.camera.center for view in scene.train])
    return int(torch.argmin((centres - camera.center).norm(dim=-1)))


def fit_held_out_pose(
    pipeline: Pipeline, scene: SceneData, camera: Camera, photo: Tensor, response: Tensor, exposure: float
) -> tuple[Camera, dict[str, float]]:
    """`camera` with its pose fitted to the LEFT half of `photo` [H, W, 3], the model frozen, by Adam on
    the squared error of the canonical render at `exposure` seconds: a rigid correction like a training
    view's (core.camera_optimizer), and the view's exposure and white balance with it. The fit starts
    from the world motion that refinement gave the nearest training view. Returns the camera and the
    size of its change from the pose as given."""
    given = camera.c2w.float()
    start = given
    if pipeline.poses is not None:
        nearest = nearest_training_view(scene, camera)
        nearest_given = scene.train[nearest].camera.c2w.float()
        with torch.no_grad():
            start = nearest_given @ pipeline.poses.correction(nearest) @ torch.linalg.inv(nearest_given) @ given
    camera = dataclasses.replace(camera, c2w=start)
    corrections = PoseCorrections(1, scene.scene_info().extent, getattr(pipeline.poses, "mode", "SO3xR3"))
    tangent = corrections.corrections[0]
    middle = photo.shape[1] // 2
    target = photo[:, :middle].reshape(-1, 3)
    if pipeline.backbone.render_chunk is not None:  # the same rays every step: a fit to noise would wander
        left_pixels = camera.pixel_centers().reshape(camera.height, camera.width, 2)[:, :middle].reshape(-1, 2)
        rays = torch.randperm(len(left_pixels), generator=torch.Generator().manual_seed(0))[:POSE_FIT_RAYS]
        target = target[rays]

    def left_render() -> Tensor:
        refined = corrections.refine(camera, 0)
        if pipeline.backbone.render_chunk is None:
            _, output = pipeline.forward(refined, exposure)
            return output.ldr.clamp(0.0, 1.0)[:, :middle].reshape(-1, 3)
        _, output = pipeline.forward(refined.with_pixels(left_pixels[rays]), exposure)
        return output.ldr.clamp(0.0, 1.0).reshape(-1, 3)

    with torch.enable_grad():
        log_scales = fit_log_scales(left_render().detach(), target, response).requires_grad_(True)
        optimizer = torch.optim.Adam([tangent, log_scales], lr=POSE_FIT_LR[0])
        decay = (POSE_FIT_LR[1] / POSE_FIT_LR[0]) ** (1 / max(POSE_FIT_STEPS - 1, 1))
        best = (math.inf, tangent.detach().clone())
        for _ in range(POSE_FIT_STEPS):
            loss = torch.mean((brighten(left_render(), log_scales, response) - target) ** 2)
            best = min(best, (float(loss.detach()), tangent.detach().clone()), key=lambda pair: pair[0])
            tangent.grad, log_scales.grad = torch.autograd.grad(loss, [tangent, log_scales])
            optimizer.step()
            for group in optimizer.param_groups:
                group["lr"] *= decay
        tangent.data.copy_(best[1])  # the best pose seen, not the last: Adam may leave a minimum it found
    with torch.no_grad():
        fitted = dataclasses.replace(camera, c2w=start @ corrections.correction(0))
        change = torch.linalg.inv(given) @ fitted.c2w
    return fitted, {
        "appearance_fitted_pose_degrees": rotation_angle_degrees(change[:3, :3]),
        "appearance_fitted_pose_translation": float(change[:3, 3].norm()),
    }
