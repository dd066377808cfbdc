"""Fitting a trained model's radiance scale on its training views (the estimator: core.calibration).

It reads HDR ground truth only of the views training read it of (--hdr-view-ratio): a run trained
without HDR views is calibrated in the units its photos' exposures define, never in those of ground
truth it was not given (only evaluation may read that).

The trainer refits it before every evaluation and checkpoint, so a saved model's HDR is always in
the capture's units; `load_trained_model` fits one for a checkpoint written before it existed.
"""

from dataclasses import dataclass

import torch
from torch import Tensor

from mono_hdr_plugin.core.calibration import RadianceCalibration, Units, fit_scale
from mono_hdr_plugin.core.exposure import decode
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.training.hdr_prior import camera_response, ground_truth_views, hdr_basis
from mono_hdr_plugin.training.pipeline import Pipeline

CALIBRATION_VIEWS = 8
"""Training views the scale is fitted on, spread over the capture."""
RAYS_PER_VIEW = 4096
"""Pixels sampled per view from a ray-based backbone (one that renders pixel batches): a full-size
render of every calibration view would cost as much as an evaluation."""


@dataclass
class TrainingSamples:
    """Pixels of one training view: the model's calibrated HDR [N, 3], the photo [N, 3], the HDR
    ground truth [N, 3] (None where the view has none), and the view's exposure in seconds."""

    hdr: Tensor
    photo: Tensor
    truth: Tensor | None
    exposure: float


@torch.no_grad()
def training_samples(
    pipeline: Pipeline, scene: SceneData, hdr_views: list[bool] | None = None
) -> list[TrainingSamples]:
    """Rendered pixels of up to CALIBRATION_VIEWS training views, the same pixels at every call
    (so a refit moves with the model only); the HDR ground truth of those `hdr_views` picks (None: all)."""
    generator = torch.Generator().manual_seed(0)
    readable = ground_truth_views(scene, hdr_views)
    samples = []
    with pipeline.evaluating():
        for index in calibration_views(scene):
            view = scene.train[index]
            hdr, rows, cols = _render_pixels(pipeline, view, generator)
            truth = view.hdr[rows, cols] if readable[index] and view.hdr is not None else None
            samples.append(TrainingSamples(hdr, view.image[rows, cols], truth, _exposure(pipeline, scene, index)))
    return samples


def fit_radiance_calibration(
    pipeline: Pipeline, scene: SceneData, step: int | None = None, hdr_views: list[bool] | None = None
) -> RadianceCalibration:
    """The radiance calibration of `pipeline` trained on `scene`: in the units of the HDR ground truth of
    the training views `hdr_views` picks (None: all) where they have some, else in those their
    exposure times define."""
    samples = training_samples(pipeline, scene, hdr_views)
    basis = hdr_basis(scene, hdr_views, pipeline.exposures)
    with_truth = [sample for sample in samples if sample.truth is not None]
    units: Units
    if with_truth:
        units, targets = "ground_truth", [sample.truth for sample in with_truth if sample.truth is not None]
    else:
        units, response = _exposure_units(scene), camera_response(scene, pipeline.exposures)
        targets = [decode(sample.photo, response) / sample.exposure for sample in samples]
    used = with_truth or samples
    scale, count = fit_scale(
        torch.cat(targets),
        torch.cat([sample.hdr for sample in used]) / pipeline.calibration.scale,  # the method's own scale
        torch.cat([sample.photo for sample in used]),
    )
    if count == 0:
        return RadianceCalibration(step=step, basis=basis)
    return RadianceCalibration(scale=scale, units=units, samples=count, step=step, basis=basis)


def calibration_views(scene: SceneData) -> list[int]:
    """Up to CALIBRATION_VIEWS training views, evenly spread."""
    count = len(scene.train)
    picks = min(count, CALIBRATION_VIEWS)
    return sorted({round(i * (count - 1) / max(picks - 1, 1)) for i in range(picks)})


def _render_pixels(pipeline: Pipeline, view: View, generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """HDR [N, 3] of a training view and the rows / cols of its pixels: the whole image from a
    backbone that renders whole images, RAYS_PER_VIEW random pixels from a ray-based one."""
    camera = view.camera
    if pipeline.backbone.pixel_batch is None:
        frame = pipeline.render(camera, view.exposure)
        rows, cols = torch.meshgrid(torch.arange(camera.height), torch.arange(camera.width), indexing="ij")
        return frame.hdr.reshape(-1, 3), rows.reshape(-1), cols.reshape(-1)
    pixels = camera.height * camera.width
    flat = torch.randperm(pixels, generator=generator)[:RAYS_PER_VIEW]
    rows, cols = flat // camera.width, flat % camera.width
    centres = torch.stack([cols.float() + 0.5, rows.float() + 0.5], -1)
    return pipeline.render(camera.with_pixels(centres), view.exposure).hdr, rows, cols


def _exposure_units(scene: SceneData) -> Units:
    return "reference_exposure" if scene.metadata.get("unknown_exposures") else "exposure_seconds"


def _exposure(pipeline: Pipeline, scene: SceneData, index: int) -> float:
    """Training view `index`'s exposure in seconds as the model sees it (learned where it is learned)."""
    if pipeline.exposures is None:
        return scene.train[index].exposure
    return float(pipeline.exposures.reference_exposure * pipeline.exposures.relative_exposures()[index])
