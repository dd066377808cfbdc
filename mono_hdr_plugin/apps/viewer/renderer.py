"""The viewer's render function: a viewer camera and display settings in, an image out, and the
saving of a shown view."""

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import numpy as np
import torch

from mono_hdr_plugin.apps.camera_paths import ViewerCamera, camera_from_viewer, focus_point, scene_up
from mono_hdr_plugin.apps.display import OUTPUT_LABELS, colour_map, needs_render_at, to_display, to_uint8
from mono_hdr_plugin.apps.viewer.snapshots import ModelSnapshots, Snapshot
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.metrics import hdr_metrics, normalise_hdr, psnr
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import write_exr, write_png
from mono_hdr_plugin.training.evaluation import first_per_camera
from mono_hdr_plugin.training.frames import ExposureModel, calibrate
from mono_hdr_plugin.training.pipeline import Frame

ERROR_OUTPUTS = {"error-hdr": "Error vs ground truth (HDR)", "error-ldr": "Error vs ground truth (LDR)"}
VIEWER_OUTPUTS = {**OUTPUT_LABELS, **ERROR_OUTPUTS}
# Largest per-pixel error the error maps show at full colour (mu-law or LDR units).
ERROR_SCALE = 0.25


@dataclass
class ViewerImage:
    """What the viewer shows: uint8 [H, W, 3], the frame it came from, and a line of text."""

    image: np.ndarray
    frame: Frame | None
    note: str = ""


class ViewerRenderer:
    """The viewer's render function: a viewer camera and display settings in, an image out.

    Knows nothing of viser; the live viewer calls it from its render threads.
    """

    def __init__(self, snapshots: ModelSnapshots, scene: SceneData):
        self.snapshots, self.scene = snapshots, scene
        cameras = [view.camera for view in scene.train]
        self.near, self.far = min(c.near for c in cameras), max(c.far for c in cameras)
        self.up, self.focus = scene_up(cameras), focus_point(scene, cameras)
        self.views = {
            f"{split}: {view.stem}": view
            for split, views in (("train", scene.train), ("test", scene.test))
            for view in first_per_camera(views)
        }
        self._exposure_models: dict[int, ExposureModel] = {}
        self._exposure_lock = threading.Lock()

    def exposure_model(self, snapshot: Snapshot) -> ExposureModel:
        """The snapshot's exposure model, fitted once per snapshot."""
        with self._exposure_lock:
            if snapshot.version not in self._exposure_models:
                self._exposure_models = {snapshot.version: calibrate(snapshot.pipeline, self.scene)}
            return self._exposure_models[snapshot.version]

    def camera(self, viewer_camera: ViewerCamera, height: int) -> Camera:
        return camera_from_viewer(viewer_camera, height, self.near, self.far)

    def render(
        self,
        viewer_camera: ViewerCamera,
        height: int,
        output: str,
        ev: float,
        cached: Frame | None = None,
        cancelled: Callable[[], bool] | None = None,
    ) -> ViewerImage:
        """The image of `output` at `ev` stops from the training exposure, `height` pixels high
        at the viewer's aspect. `cached`: a frame of the same camera and model to re-display
        when the output allows (exposure changes need no render outside the camera response)."""
        snapshot = self.snapshots.latest()
        model = self.exposure_model(snapshot)
        exposure = model.exposure_at(ev)
        if output in ERROR_OUTPUTS:
            return self._error_image(snapshot, model, viewer_camera, height, output, exposure)
        if output not in OUTPUT_LABELS:
            raise ValueError(f"unknown output {output!r}; choose one of {', '.join(VIEWER_OUTPUTS)}")
        render_exposure = exposure if needs_render_at(output, model) else model.reference_exposure
        frame = cached
        wants_depth = output == "depth"
        if (
            frame is None
            or frame.exposure != render_exposure
            or frame.hdr.shape[0] != height
            or (wants_depth and frame.depth is None)
        ):
            frame = snapshot.pipeline.render(
                self.camera(viewer_camera, height), render_exposure, cancelled, with_depth=wants_depth
            )
        note = "this backbone renders no depth" if output == "depth" and frame.depth is None else ""
        return ViewerImage(to_uint8(to_display(frame, output, exposure, model)), frame, note)

    def dataset_view(self, viewer_camera: ViewerCamera, exposure: float) -> View | None:
        """The dataset view at the viewer's pose (within a thousandth of the scene size), the one
        nearest in exposure where the pose was photographed at several."""
        pose = self.camera(viewer_camera, 8).c2w
        size = float((self.scene.bounds_max - self.scene.bounds_min).norm())
        at_pose = [
            view
            for view in self.scene.train + self.scene.test
            if (view.camera.center - pose[:3, 3]).norm() < 1e-3 * size
            and torch.allclose(view.camera.c2w[:3, :3], pose[:3, :3], atol=1e-3)
        ]
        return min(at_pose, key=lambda v: abs(math.log(v.exposure / exposure)), default=None)

    def _error_image(
        self,
        snapshot: Snapshot,
        model: ExposureModel,
        viewer_camera: ViewerCamera,
        height: int,
        output: str,
        exposure: float,
    ) -> ViewerImage:
        view = self.dataset_view(viewer_camera, exposure)
        width = max(1, round(height * viewer_camera.aspect))
        if view is None:
            return ViewerImage(
                np.full((height, width, 3), 40, np.uint8),
                None,
                "go to a dataset camera (Camera) to compare with its ground truth",
            )
        if output == "error-hdr":
            if view.hdr is None:
                return ViewerImage(
                    np.full((height, width, 3), 40, np.uint8),
                    None,
                    f"{view.stem} has no HDR ground truth: choose the LDR error",
                )
            frame = snapshot.pipeline.render(view.camera, model.reference_exposure)
            error = (normalise_hdr(frame.hdr) - normalise_hdr(view.hdr)).abs().mean(-1)
            note = f"{view.stem}: HDR PSNR {hdr_metrics(frame.hdr, view.hdr)['hdr_psnr']:.2f} dB (mu-law, own max)"
        else:
            render_exposure = view.exposure if model.renders_any_exposure else model.reference_exposure
            frame = snapshot.pipeline.render(view.camera, render_exposure)
            ldr = to_display(frame, "ldr", view.exposure, model)
            error = (ldr - view.image).abs().mean(-1)
            note = f"{view.stem} at {view.exposure:g} s: LDR PSNR {psnr(ldr, view.image):.2f} dB"
        image = to_uint8(colour_map(error / ERROR_SCALE, "magma"))
        return ViewerImage(letterbox(image, viewer_camera.aspect), frame, note + f"; full colour = {ERROR_SCALE} error")


def letterbox(image: np.ndarray, aspect: float, fill: int = 40) -> np.ndarray:
    """`image` centred on a canvas of width / height = aspect, so the viewer does not stretch it."""
    height, width = image.shape[:2]
    canvas_height, canvas_width = max(height, round(width / aspect)), max(width, round(height * aspect))
    canvas = np.full((canvas_height, canvas_width, 3), fill, np.uint8)
    top, left = (canvas_height - height) // 2, (canvas_width - width) // 2
    canvas[top : top + height, left : left + width] = image
    return canvas


def save_view(out: Path, frame: Frame, image: np.ndarray, output: str) -> list[Path]:
    """OUT/view_<time>_hdr.exr (linear HDR) and OUT/view_<time>_<output>.png (what is shown); each
    file appears complete or not at all."""
    stem = f"view_{datetime.now().strftime('%Y%m%d-%H%M%S-%f')}"
    paths = [out / f"{stem}_hdr.exr", out / f"{stem}_{output}.png"]
    write_exr(paths[0], frame.hdr.float().numpy())
    write_png(paths[1], image.astype(np.float32) / 255.0)
    return paths
