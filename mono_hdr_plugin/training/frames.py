"""A trained model as linear images: the one rendering path of the viewer, camera-path videos,
exposure sweeps and exports.

Everything here renders through `Pipeline.render` (the one render path, also used by
evaluation); checkpoints load through `training.trained.load_trained_model`.
"""

import math
from dataclasses import dataclass

import torch

from mono_hdr_plugin.core.calibration import fit_scale
from mono_hdr_plugin.core.colour import srgb_decode
from mono_hdr_plugin.core.exposure import reference_view
from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.training.calibration import training_samples
from mono_hdr_plugin.training.pipeline import Pipeline


@dataclass(frozen=True)
class ExposureModel:
    """How a model's renders relate to exposure time.

    reference_exposure: seconds shown at EV 0 (the training exposure; of several, the reference
        view's, `core.exposure.reference_view`).
    display_scale: k in `linear display value = k * hdr * t / reference_exposure`. HDR renders
        are calibrated (core.calibration), but in units that need not be the display's (a ground
        truth's), so k is fitted: the sRGB-decoded training photos, brought to the reference
        exposure, equal k * hdr over their well-exposed pixels (median ratio, core.calibration.fit_scale).
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


@torch.no_grad()
def calibrate(pipeline: Pipeline, scene: SceneData) -> ExposureModel:
    """The ExposureModel of a model trained on `scene`: its display scale is fitted on the training
    views' photos, so at EV 0 and a training view's exposure the HDR display shows that photo."""
    exposures = scene.train_exposures
    reference = scene.train[reference_view(scene.train)].exposure  # the training's own reference view
    samples = training_samples(pipeline, scene)
    display_scale, _ = fit_scale(
        torch.cat([srgb_decode(sample.photo) * (reference / sample.exposure) for sample in samples]),
        torch.cat([sample.hdr for sample in samples]),
        torch.cat([sample.photo for sample in samples]),
    )
    return ExposureModel(
        reference_exposure=reference,
        display_scale=display_scale,
        renders_any_exposure=pipeline.renders_any_exposure,
        ldr_exposures=tuple(exposures) if len(exposures) == 1 else (),
    )
