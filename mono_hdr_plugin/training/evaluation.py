"""Test-view metrics of a pipeline, and the EXR/PNG files a render of a view writes."""

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from mono_hdr_plugin.core.exposure import decode
from mono_hdr_plugin.core.metrics import (
    CHANNELS,
    OWN_LDR_PREFIX,
    LpipsUnavailable,
    chroma_outliers,
    clipped_split_metrics,
    hdr_metrics,
    hdr_scale_metrics,
    load_lpips,
    lpips_distance,
    normalise_hdr,
    psnr,
    radiance_consistency,
    radiance_warnings,
    source_metrics,
    ssim,
    tone_mapped_pair,
)
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import write_exr, write_png
from mono_hdr_plugin.training.appearance import (
    APPEARANCE_PROTOCOL,
    appearance_fitted_scores,
    appearance_protocol_runs,
    fit_held_out_pose,
    match_exposure,
    reference_exposure,
)
from mono_hdr_plugin.training.hdr_prior import camera_response
from mono_hdr_plugin.training.pipeline import Frame, Pipeline


def first_per_camera(views: list[View]) -> list[View]:
    """One view per camera pose (view_id), the first of its exposures: HDR is rendered once per camera."""
    seen: set[int] = set()
    first: list[View] = []
    for view in views:
        if view.view_id not in seen:
            seen.add(view.view_id)
            first.append(view)
    return first


def evaluation_views(pipeline: Pipeline, scene: SceneData, max_eval_views: int | None = None) -> list[View]:
    """Test views at exposures the method can render, from the first `max_eval_views` cameras."""
    train_exposures = set(scene.train_exposures)
    views = [v for v in scene.test if pipeline.renders_any_exposure or v.exposure in train_exposures]
    if not views:
        raise ValueError(
            f"scene {scene.name!r} has no test view at a training exposure "
            f"({sorted(train_exposures)}) for method {pipeline.method_name!r}"
        )
    view_ids = set(sorted({v.view_id for v in views})[:max_eval_views])
    return [v for v in views if v.view_id in view_ids]


HDR_KEYS = (
    "hdr_psnr",
    "hdr_ssim",
    "hdr_psnr_gt_max",
    "hdr_ssim_gt_max",
    "hdr_psnr_aligned",
    "hdr_psnr_masked",
    "hdr_median_ratio",
    "hdr_peak_ratio",
    "ldr_peak_ratio",
    "chroma_outliers",
    "hdr_psnr_clipped",
    "hdr_psnr_unclipped",
    "clipped_fraction",
)
APPEARANCE_KEYS = ("ldr_psnr_appearance_fitted", "ldr_ssim_appearance_fitted")
"""LDR scores of the appearance protocol (training.appearance): right half, appearance fitted on the left."""
RADIANCE_KEYS = tuple(
    f"{prefix}{score}_{c}"
    for prefix in ("hdr_", OWN_LDR_PREFIX)
    for score in ("rank_correlation", "log_slope")
    for c in CHANNELS
)
"""Scores of the HDR against the test photos themselves and against the model's own LDR renders of them
(core.metrics.radiance_consistency): every run has them."""


@torch.no_grad()
def evaluate(
    pipeline: Pipeline,
    scene: SceneData,
    max_eval_views: int | None = None,
    render_dir: Path | None = None,
    eval_appearance: str = "auto",
    eval_pose: str = "auto",
) -> dict[str, Any]:
    """Metrics on the test views, in eval mode: LDR at each exposure the method can render, HDR per camera.

    The headline LDR figures average the exposures the model was trained at (t1/t3/t5), each
    exposure the mean of its views; HDR figures (of the calibrated HDR, `Pipeline.calibration`) are
    mu-law with both official normalisations, aligned and emitter-masked (core.metrics), the mean over
    cameras (docs/method.md). "views" lists every evaluated view's own figures.
    With `render_dir`, each camera's renders are written there (`save_view_renders`). With the appearance
    protocol (`eval_appearance`, training.appearance) every view is also scored with its exposure and
    white balance (and, with `eval_pose`, its pose) fitted on the left half of its photo, on the right half.
    """
    views = evaluation_views(pipeline, scene, max_eval_views)
    lpips_model, lpips_skipped = _lpips_or_reason()
    first = first_per_camera(views)
    cameras = {id(v) for v in first}
    hdr_views = {id(v) for v in first if v.hdr is not None}
    # Views of unknown exposure are rendered at the exposure that fits their photo best (one number each).
    fitted = set(scene.metadata.get("unknown_exposures", ())) if pipeline.exposures is not None else set()
    fitting = Fitting.of(pipeline, scene, eval_appearance, eval_pose)
    with pipeline.evaluating():
        rows = [
            _score_view(
                pipeline,
                view,
                fitting.with_exposure(view.name in fitted),
                id(view) in hdr_views,
                id(view) in cameras,
                lpips_model,
                render_dir,
            )
            for view in views
        ]
    metrics = _summarise_rows(pipeline, scene, rows)
    if fitting.appearance:
        metrics["appearance_protocol"] = APPEARANCE_PROTOCOL + (POSE_PROTOCOL if fitting.pose else "")
    metrics["radiance_scale"] = pipeline.calibration.scale
    metrics["radiance_units"] = pipeline.calibration.units
    metrics["hdr_basis"] = pipeline.calibration.basis
    metrics["scene_extent"] = scene.metadata.get("extent_reason", "bounded")
    metrics["test_views"] = len({v.view_id for v in views})
    metrics["ldr_exposure_fitted"] = sum(view.name in fitted for view in views)
    for key in (*HDR_KEYS, *RADIANCE_KEYS, "lpips_ldr", "lpips_hdr"):
        values = [row[key] for row in rows if key in row and not math.isnan(row[key])]  # NaN: no pixel to score
        metrics[key] = _mean(values) if values else None
    peaks = [row["hdr_peak_ratio"] for row in rows if "hdr_peak_ratio" in row]
    # A mean of ratios hides a lost source behind an overshoot elsewhere: the worst view, in stops.
    metrics["hdr_peak_ratio_worst"] = max(peaks, key=lambda r: abs(math.log(max(r, 1e-12)))) if peaks else None
    metrics["hdr_warnings"] = radiance_warnings(metrics)
    if lpips_skipped:
        metrics["lpips_skipped"] = lpips_skipped
    metrics["views"] = rows
    return metrics


def _lpips_or_reason() -> tuple[Any, str | None]:
    """The LPIPS model, or None and why it is unavailable (the scores are then skipped, not failed)."""
    try:
        return load_lpips(), None
    except LpipsUnavailable as reason:
        return None, str(reason)


@dataclass
class Fitting:
    """What of a test view's appearance evaluation fits to its photo, through the camera `response`.

    exposure: the view's exposure is unknown (one exposure fitted on the whole photo, the "as given"
    score); appearance: the appearance protocol runs (training.appearance); pose: the appearance
    protocol fits the view's pose too (`fit_held_out_pose`, on `scene`). All brighten the canonical
    render at `reference_exposure` seconds."""

    response: torch.Tensor
    reference_exposure: float
    appearance: bool
    pose: bool
    scene: SceneData
    exposure: bool = False

    @classmethod
    def of(cls, pipeline: Pipeline, scene: SceneData, eval_appearance: str, eval_pose: str) -> "Fitting":
        """The fits of `evaluate` (the exposure one is set per view, `with_exposure`)."""
        pose = pose_fit_runs(pipeline, eval_pose)
        protocol = pose or appearance_protocol_runs(pipeline, eval_appearance)
        return cls(
            camera_response(scene, pipeline.exposures), reference_exposure(pipeline, scene), protocol, pose, scene
        )

    def with_exposure(self, exposure: bool) -> "Fitting":
        return dataclasses.replace(self, exposure=exposure)

    def renders_reference(self) -> bool:
        return self.exposure or self.appearance


POSE_PROTOCOL = " (the pose fitted on the left half too)"


def pose_fit_runs(pipeline: Pipeline, setting: str) -> bool:
    """--eval-pose: on, off, or auto (on where training refined its poses and the backbone can fit one)."""
    differentiable = pipeline.backbone.differentiable_pose
    if setting == "on" and not differentiable:
        raise FlagError(
            f"--eval-pose on: the backbone {pipeline.backbone_name!r} renders without gradients to the camera "
            "pose, so a held-out pose cannot be fitted; pass --eval-pose off"
        )
    if setting == "auto":
        return pipeline.poses is not None and differentiable
    return setting == "on"


def _render_view(pipeline: Pipeline, view: View, fitting: Fitting) -> tuple[Frame, Frame | None]:
    """The view's render as scored (at its exposure, or at the one fitted to its photo) and, when a fit
    needs it, the canonical render at the reference exposure (one render where both are that one)."""
    reference = pipeline.render(view.camera, fitting.reference_exposure) if fitting.renders_reference() else None
    if fitting.exposure:
        assert reference is not None
        return match_exposure(reference, view.image, fitting.response), reference
    return pipeline.render(view.camera, view.exposure), reference


def _score_view(
    pipeline: Pipeline,
    view: View,
    fitting: Fitting,
    score_hdr: bool,
    score_radiance: bool,
    lpips_model,
    render_dir: Path | None,
) -> dict[str, Any]:
    """One view's own figures: LDR always (and appearance fitted where `fitting` says), HDR against its
    ground truth (and its renders under `render_dir`) when `score_hdr`, HDR against the photo
    linearised through the response when `score_radiance`."""
    output, reference = _render_view(pipeline, view, fitting)
    ldr = output.ldr  # a Frame's LDR is clamped to [0, 1]: scored as a photo would be
    row = {
        "view": view.stem,
        "view_id": view.view_id,
        "exposure": view.exposure,
        "ldr_psnr": psnr(ldr, view.image),
        "ldr_ssim": ssim(ldr.double(), view.image.double()).item(),
    }
    if fitting.appearance:
        assert reference is not None
        if fitting.pose:
            camera, pose_change = fit_held_out_pose(
                pipeline, fitting.scene, view.camera, view.image, fitting.response, fitting.reference_exposure
            )
            reference = pipeline.render(camera, fitting.reference_exposure)
            row.update(pose_change)
        row.update(appearance_fitted_scores(reference, view.image, fitting.response))
    if lpips_model is not None:
        row["lpips_ldr"] = lpips_distance(lpips_model, ldr, view.image)
    if score_radiance:
        row.update(radiance_consistency(output.hdr, decode(view.image, fitting.response), view.image))
        row.update(radiance_consistency(output.hdr, decode(ldr, fitting.response), ldr, OWN_LDR_PREFIX))
    if score_hdr:
        assert view.hdr is not None  # score_hdr is set only for views with a ground-truth HDR
        row.update(hdr_metrics(output.hdr, view.hdr))
        row.update(hdr_scale_metrics(output.hdr, view.hdr, view.image))
        row.update(source_metrics(output.hdr, view.hdr, ldr, view.image))
        row["chroma_outliers"] = chroma_outliers(output.hdr, view.hdr, view.image)
        row.update(clipped_split_metrics(output.hdr, view.hdr, view.image))
        if lpips_model is not None:
            row["lpips_hdr"] = lpips_distance(lpips_model, *tone_mapped_pair(output.hdr, view.hdr, "own_max"))
        if render_dir is not None:
            save_view_renders(render_dir, view, output)
    return row


def _summarise_rows(pipeline: Pipeline, scene: SceneData, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The run's names and the LDR figures: per exposure the mean of its views, the headline the mean
    over the training exposures (over every exposure when none of them was evaluated); the appearance
    protocol's the same way where it ran (views too narrow for its SSIM left out)."""
    exposures = sorted({row["exposure"] for row in rows})
    train_exposures = set(scene.train_exposures)
    headline = [e for e in exposures if e in train_exposures] or exposures
    keys = ("ldr_psnr", "ldr_ssim", *(key for key in APPEARANCE_KEYS if key in rows[0]))

    def mean_of(key: str, exposure: float) -> float:
        values = [row[key] for row in rows if row["exposure"] == exposure and not math.isnan(row[key])]
        return _mean(values)

    by_exposure = {key: {e: mean_of(key, e) for e in exposures} for key in keys}
    summary: dict[str, Any] = {"backbone": pipeline.backbone_name, "method": pipeline.method_name, "scene": scene.name}
    for key in keys:
        value = _mean([by_exposure[key][e] for e in headline if not math.isnan(by_exposure[key][e])])
        summary[key] = None if math.isnan(value) and key in APPEARANCE_KEYS else value
    for key in ("ldr_psnr", "ldr_ssim"):
        summary[f"{key}_per_exposure"] = {f"{e:g}": value for e, value in by_exposure[key].items()}
    return summary


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def save_view_renders(render_dir: Path, view: View, output: Frame) -> list[Path]:
    """save_hdr_renders plus <stem>_ldr.png, the LDR render at the view's exposure."""
    path = render_dir / f"{view.stem}_ldr.png"
    write_png(path, output.ldr.numpy())  # write_png clips to [0, 1]
    return [*save_hdr_renders(render_dir, view, output.hdr), path]


def save_hdr_renders(render_dir: Path, view: View, hdr: torch.Tensor) -> list[Path]:
    """<stem>_hdr.exr (linear) and <stem>_hdr_mulaw.png (tone-mapped for display) of an HDR render."""
    paths = [render_dir / f"{view.stem}_hdr.exr", render_dir / f"{view.stem}_hdr_mulaw.png"]
    write_exr(paths[0], hdr.numpy())
    write_png(paths[1], normalise_hdr(hdr).numpy())
    return paths
