"""A trained model as linear images: the one rendering path of the viewer, camera-path videos,
exposure sweeps and exports.

Everything here renders through `Pipeline.render` (the one render path, also used by
evaluation); checkpoints load through `training.trained.load_trained_model`.
"""

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from mono_hdr_plugin.core.colour import srgb_decode
from mono_hdr_plugin.core.exposure import reference_view
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.pipeline import Pipeline

# Pixels whose LDR value lies in this range are neither clipped nor lost in noise: the display
# scale is fitted on them.
WELL_EXPOSED = (0.05, 0.95)
# Long side of the training views rendered to fit the display scale: a few thousand pixels suffice.
CALIBRATION_SIZE = 48
CALIBRATION_VIEWS = 3


@dataclass(frozen=True)
class ExposureModel:
    """How a model's renders relate to exposure time.

    reference_exposure: seconds shown at EV 0 (the training exposure; of several, the reference
        view's, `core.exposure.reference_view`).
    display_scale: k in `linear display value = k * hdr * t / reference_exposure`. HDR renders
        have no absolute scale (Mono-HDR's losses normalise by the maximum), so k is fitted: at
        the reference exposure the sRGB-decoded LDR render equals k * hdr over well-exposed pixels
        of the training views (median ratio).
    ldr_exposures: exposures at which the method's own LDR output is a photo at that exposure.
        Empty when it renders any exposure (the baselines' learned camera response), else the
        single training exposure of Mono-HDR's LDR branch (none after multi-exposure training,
        where the branch is an average).
    """

    reference_exposure: float
    display_scale: float
    renders_any_exposure: bool
    ldr_exposures: tuple[float, ...] = ()

    def shows_own_ldr(self, exposure: float) -> bool:
        """Whether the method's LDR output is the photo at `exposure`."""
        return self.renders_any_exposure or any(math.isclose(exposure, t, rel_tol=1e-6) for t in self.ldr_exposures)

    def exposure_at(self, ev: float) -> float:
        return self.reference_exposure * 2.0**ev

    def ev_of(self, exposure: float) -> float:
        return math.log2(exposure / self.reference_exposure)


def fit_display_scale(ldr: Tensor, hdr: Tensor) -> float:
    """k with srgb_decode(ldr) ~ k * hdr: the median ratio over well-exposed, lit pixel values;
    a mid-grey mapping of the median radiance when no pixel qualifies."""
    low, high = WELL_EXPOSED
    usable = (ldr > low) & (ldr < high) & (hdr > 1e-8)
    if usable.sum() >= 16:
        return float((srgb_decode(ldr[usable]) / hdr[usable]).median())
    lit = hdr[hdr > 1e-8]
    return 0.18 / float(lit.median()) if lit.numel() else 1.0


@torch.no_grad()
def calibrate(pipeline: Pipeline, scene: SceneData) -> ExposureModel:
    """The ExposureModel of a model trained on `scene` (renders a few small training views)."""
    exposures = scene.train_exposures
    reference = scene.train[reference_view(scene.train)].exposure  # the training's own reference view
    views = {view.view_id: view for view in scene.train}
    chosen = list(views.values())[:: max(1, len(views) // CALIBRATION_VIEWS)][:CALIBRATION_VIEWS]
    ldr, hdr = [], []
    for view in chosen:
        factor = min(1.0, CALIBRATION_SIZE / max(view.camera.width, view.camera.height))
        frame = pipeline.render(view.camera.scaled(factor), reference)
        ldr.append(frame.ldr.reshape(-1))
        hdr.append(frame.hdr.reshape(-1))
    return ExposureModel(
        reference_exposure=reference,
        display_scale=fit_display_scale(torch.cat(ldr), torch.cat(hdr)),
        renders_any_exposure=pipeline.renders_any_exposure,
        ldr_exposures=tuple(exposures) if len(exposures) == 1 else (),
    )
