"""`mono-hdr view` and `mono-hdr train ... --viewer`: a live viewer in the browser (viser).

Controls: exposure (EV slider and exposure time), output (LDR through the camera response,
HDR through sRGB, filmic or mu-law, depth, error against ground truth), jump to any dataset
camera, resolution that drops while the camera moves, and saving the view as EXR + PNG.

Threads. viser runs its own event loop and calls our GUI callbacks from a thread pool; each
connected browser gets one render thread (`_ClientLoop`). During training the model lives
in the training thread, which must never wait for rendering, so the two share it through
`ModelSnapshots`: the training thread, between two steps, deep-copies the pipeline
(a few MB, at most every `SnapshotPublisher.min_interval` seconds and only while a browser is
connected) and swaps the copy in under a lock that guards nothing but that one reference.
A published snapshot is never modified again, so render threads use it without any lock
while training goes on with the live model.
"""

import copy
import math
import signal
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Callable, ClassVar

import numpy as np
import torch
from rich.console import Console

from mono_hdr_plugin.apps.camera_paths import ViewerCamera, camera_from_viewer, focus_point, scene_up, viewer_from_camera
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import write_exr, write_png
from mono_hdr_plugin.training.evaluation import first_per_camera
from mono_hdr_plugin.apps.display import OUTPUT_LABELS, colour_map, needs_render_at, to_display, to_uint8
from mono_hdr_plugin.training.frames import ExposureModel, calibrate, load_model
from mono_hdr_plugin.core.metrics import hdr_metrics, normalise_hdr, psnr
from mono_hdr_plugin.training.pipeline import Frame, Pipeline, RenderCancelled
from mono_hdr_plugin.training.hooks import TrainingHook
from mono_hdr_plugin.core.validation import at_least, between

console = Console(stderr=True)
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
ERROR_OUTPUTS = {"error-hdr": "Error vs ground truth (HDR)", "error-ldr": "Error vs ground truth (LDR)"}
VIEWER_OUTPUTS = {**OUTPUT_LABELS, **ERROR_OUTPUTS}
# Largest per-pixel error the error maps show at full colour (mu-law or LDR units).
ERROR_SCALE = 0.25
# While the camera moves, frames aim at this many seconds; it counts as still after MOVE_SETTLE s.
MOVING_FRAME_SECONDS = 0.1
MOVE_SETTLE = 0.3
MIN_HEIGHT = 24
# During training, re-render a still view for a new snapshot at most this often.
TRAINING_REFRESH = 2.0


@dataclass
class ViewConfig:
    """Look at a trained model in the browser: exposure, tone mapping, depth, errors, dataset cameras."""

    checkpoint: Path
    """A checkpoint written by `mono-hdr train`."""
    port: int = 7007
    """Port to listen on (the next free one when taken; 0: any free port)."""
    host: str = "127.0.0.1"
    """Address to listen on. The default admits this machine only; 0.0.0.0 opens the viewer to
    the network, with no authentication (anyone who reaches it sees the model and can save views)."""
    out: Path = Path("outputs/viewer")
    """Folder for views saved with the viewer's Save button."""
    max_resolution: int = 512
    """Longest side of a still frame in pixels (a slider in the viewer)."""

    flag_rules: ClassVar = {"port": between(0, 65535), "max_resolution": at_least(1)}


@dataclass(frozen=True)
class Snapshot:
    """A model the viewer may render; never modified after it was published."""

    pipeline: Pipeline
    step: int
    version: int


class ModelSnapshots:
    """The latest published model, shared by the thread that owns it and the render threads."""

    def __init__(self, pipeline: Pipeline, step: int, copy_model: bool = True):
        self._lock = threading.Lock()
        self._latest: Snapshot | None = None
        self.publish(pipeline, step, copy_model)

    def publish(self, pipeline: Pipeline, step: int, copy_model: bool = True) -> None:
        """Make (a frozen copy of) this model the one rendered from now on. With copy_model the
        caller may keep changing its own model: call it from the thread that changes it."""
        if copy_model:
            pipeline = copy.deepcopy(pipeline)
            pipeline.eval()
            pipeline.requires_grad_(False)
        with self._lock:
            version = 0 if self._latest is None else self._latest.version + 1
            self._latest = Snapshot(pipeline, step, version)

    def latest(self) -> Snapshot:
        with self._lock:
            return self._latest


class SnapshotPublisher(TrainingHook):
    """A training hook: publishes a copy of the model while someone watches.

    Copies are spaced so that copying takes at most 1/20 of the training time (and at least
    `min_interval` seconds apart): the viewer may lag, training barely notices.
    """

    def __init__(self, snapshots: ModelSnapshots, watched: Callable[[], bool], on_publish: Callable[[int], None],
                 min_interval: float = 1.0):
        self.snapshots, self.watched, self.on_publish = snapshots, watched, on_publish
        self.min_interval = min_interval
        self.interval = min_interval
        self.published_at = -math.inf
        self.published_step = -1

    def after_step(self, trainer, record: dict) -> None:
        if time.perf_counter() - self.published_at >= self.interval:
            self._publish(trainer)

    def on_end(self, trainer) -> None:
        # The finished model is always shown, however the copies were spaced.
        if self.published_step != trainer.step:
            self._publish(trainer)

    def _publish(self, trainer) -> None:
        if not self.watched():
            return
        now = time.perf_counter()
        self.snapshots.publish(trainer.pipeline, trainer.step)
        copy_seconds = time.perf_counter() - now
        self.interval = max(self.min_interval, 20.0 * copy_seconds)
        self.published_at = time.perf_counter()
        self.published_step = trainer.step
        self.on_publish(trainer.step)


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
        self.views = {f"{split}: {view.stem}": view
                      for split, views in (("train", scene.train), ("test", scene.test)) for view in first_per_camera(views)}
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

    def render(self, viewer_camera: ViewerCamera, height: int, output: str, ev: float,
               cached: Frame | None = None, cancelled: Callable[[], bool] | None = None) -> ViewerImage:
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
        if (frame is None or frame.exposure != render_exposure or frame.hdr.shape[0] != height
                or (wants_depth and frame.depth is None)):
            frame = snapshot.pipeline.render(self.camera(viewer_camera, height), render_exposure, cancelled,
                                             with_depth=wants_depth)
        note = "this backbone renders no depth" if output == "depth" and frame.depth is None else ""
        return ViewerImage(to_uint8(to_display(frame, output, exposure, model)), frame, note)

    def dataset_view(self, viewer_camera: ViewerCamera, exposure: float) -> View | None:
        """The dataset view at the viewer's pose (within a thousandth of the scene size), the one
        nearest in exposure where the pose was photographed at several."""
        pose = self.camera(viewer_camera, 8).c2w
        size = float((self.scene.bounds_max - self.scene.bounds_min).norm())
        at_pose = [view for view in self.scene.train + self.scene.test
                   if (view.camera.center - pose[:3, 3]).norm() < 1e-3 * size
                   and torch.allclose(view.camera.c2w[:3, :3], pose[:3, :3], atol=1e-3)]
        return min(at_pose, key=lambda v: abs(math.log(v.exposure / exposure)), default=None)

    def _error_image(self, snapshot: Snapshot, model: ExposureModel, viewer_camera: ViewerCamera, height: int,
                     output: str, exposure: float) -> ViewerImage:
        view = self.dataset_view(viewer_camera, exposure)
        width = max(1, round(height * viewer_camera.aspect))
        if view is None:
            return ViewerImage(np.full((height, width, 3), 40, np.uint8), None,
                               "go to a dataset camera (Camera) to compare with its ground truth")
        if output == "error-hdr" and view.hdr is None:
            return ViewerImage(np.full((height, width, 3), 40, np.uint8), None,
                               f"{view.stem} has no HDR ground truth: choose the LDR error")
        if output == "error-hdr":
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
    canvas[top:top + height, left:left + width] = image
    return canvas


def save_view(out: Path, frame: Frame, image: np.ndarray, output: str) -> list[Path]:
    """OUT/view_<time>_hdr.exr (linear HDR) and OUT/view_<time>_<output>.png (what is shown); each
    file appears complete or not at all."""
    stem = f"view_{datetime.now().strftime('%Y%m%d-%H%M%S-%f')}"
    paths = [out / f"{stem}_hdr.exr", out / f"{stem}_{output}.png"]
    write_exr(paths[0], frame.hdr.float().numpy())
    write_png(paths[1], image.astype(np.float32) / 255.0)
    return paths


def viewer_camera_of(client) -> ViewerCamera:
    camera = client.camera
    return ViewerCamera(wxyz=tuple(float(v) for v in camera.wxyz), position=tuple(float(v) for v in camera.position),
                        fov=float(camera.fov), aspect=float(camera.aspect))


class Viewer:
    """The viser server, its controls, and one render thread per connected browser."""

    def __init__(self, renderer: ViewerRenderer, host: str = "127.0.0.1", port: int = 7007,
                 out: Path = Path("outputs/viewer"), max_resolution: int = 512, training: bool = False):
        import viser  # noqa: PLC0415 - only the viewer needs it

        if host not in LOCAL_HOSTS:
            console.print(f"[yellow]warning: the viewer listens on {host}: anyone who can reach this machine on the "
                          "network can open it (there is no password) and save files into "
                          f"{out}. Use the default --host 127.0.0.1 with an SSH tunnel to keep it private.")
        self.renderer, self.out = renderer, out
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.settings_version = 0
        self._loops: dict[int, _ClientLoop] = {}
        self._loops_lock = threading.Lock()
        self._syncing_exposure = False
        self._place_initial_camera()
        self._add_controls(max_resolution, training)
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "::") else host
        return f"http://{host}:{self.server.get_port()}"

    def has_clients(self) -> bool:
        return bool(self._loops)

    # ---------------------------------------------------------------- set-up
    def _place_initial_camera(self) -> None:
        first = next(iter(self.renderer.views.values())).camera
        start = viewer_from_camera(first)
        self.server.scene.set_up_direction(tuple(float(v) for v in self.renderer.up))
        initial = self.server.initial_camera
        initial.position = start.position
        initial.look_at = tuple(float(v) for v in self.renderer.focus)
        initial.up = tuple(float(v) for v in self.renderer.up)
        initial.fov = start.fov

    def _add_controls(self, max_resolution: int, training: bool) -> None:
        gui = self.server.gui
        gui.configure_theme(dark_mode=True, show_share_button=False)
        self.status = gui.add_markdown("")
        if training:
            self.training_status = gui.add_markdown("**Training:** waiting for the first snapshot")
        with gui.add_folder("Exposure"):
            self.ev = gui.add_slider("EV (stops)", min=-10.0, max=10.0, step=0.1, initial_value=0.0,
                                     hint="Stops from the training exposure: +1 doubles the exposure time")
            self.exposure_time = gui.add_number("Exposure (s)", initial_value=1.0, min=1e-9, step=1e-4,
                                                hint="Exposure time in seconds (same control as EV)")
            reset = gui.add_button("Training exposure")
        with gui.add_folder("Output"):
            self.output = gui.add_dropdown("Show", tuple(VIEWER_OUTPUTS.values()), initial_value=VIEWER_OUTPUTS["ldr"])
        with gui.add_folder("Camera"):
            self.view_choice = gui.add_dropdown("Dataset camera", tuple(self.renderer.views))
            go = gui.add_button("Go to camera")
        with gui.add_folder("Resolution"):
            self.max_resolution = gui.add_slider("Longest side (px)", min=64, max=2048, step=16,
                                                 initial_value=max(64, min(2048, max_resolution)))
            self.adaptive = gui.add_checkbox("Lower while moving", initial_value=True)
        save = gui.add_button("Save view (EXR + PNG)")

        self.ev.on_update(lambda _: self._exposure_changed(from_slider=True))
        self.exposure_time.on_update(lambda _: self._exposure_changed(from_slider=False))
        reset.on_click(lambda _: setattr(self.ev, "value", 0.0))
        for control in (self.output, self.max_resolution, self.adaptive):
            control.on_update(lambda _: self.settings_changed())
        go.on_click(lambda event: self.go_to(event.client, self.view_choice.value))
        save.on_click(lambda event: self._save(event.client))
        self._sync_exposure_time()

    # ------------------------------------------------------------- callbacks
    def output_key(self) -> str:
        return next(key for key, label in VIEWER_OUTPUTS.items() if label == self.output.value)

    def _sync_exposure_time(self) -> None:
        model = self.renderer.exposure_model(self.renderer.snapshots.latest())
        self._syncing_exposure = True
        try:
            self.exposure_time.value = float(f"{model.exposure_at(self.ev.value):.6g}")
        finally:
            self._syncing_exposure = False

    def _exposure_changed(self, from_slider: bool) -> None:
        if self._syncing_exposure:
            return
        if from_slider:
            self._sync_exposure_time()
        else:
            model = self.renderer.exposure_model(self.renderer.snapshots.latest())
            ev = model.ev_of(max(float(self.exposure_time.value), 1e-9))
            self._syncing_exposure = True
            try:
                self.ev.value = round(min(10.0, max(-10.0, ev)), 1)
            finally:
                self._syncing_exposure = False
        self.settings_changed()

    def settings_changed(self) -> None:
        self.settings_version += 1
        for loop in list(self._loops.values()):
            loop.wake.set()

    def go_to(self, client, name: str) -> None:
        """Move a browser's camera to a dataset camera (pose and field of view)."""
        camera = self.renderer.views[name].camera
        target = viewer_from_camera(camera)
        distance = float((self.renderer.focus - camera.center) @ camera.c2w[:3, 2])
        with client.atomic():
            client.camera.fov = target.fov
            client.camera.position = target.position
            client.camera.wxyz = target.wxyz
            if distance > 0:
                client.camera.look_at = tuple(float(v) for v in camera.center + distance * camera.c2w[:3, 2])

    def _save(self, client) -> None:
        loop = self._loops.get(client.client_id)
        if loop is None or loop.last_image is None or loop.last_image.frame is None:
            client.add_notification("Nothing to save yet", "Wait for the first frame.", auto_close_seconds=4.0)
            return
        try:
            shown = loop.render_once(full=True)
            paths = save_view(self.out, shown.frame, shown.image, self.output_key())
        except Exception as error:  # noqa: BLE001 - a failed save is reported in the browser, the viewer goes on
            client.add_notification("Could not save", str(error), color="red")
            return
        console.print(f"saved {paths[0]} and {paths[1]}")
        client.add_notification("Saved", f"{paths[0]}\n{paths[1]}", auto_close_seconds=6.0)

    def _connect(self, client) -> None:
        loop = _ClientLoop(self, client)
        with self._loops_lock:
            self._loops[client.client_id] = loop
        client.camera.on_update(lambda _: loop.camera_moved())
        loop.start()

    def _disconnect(self, client) -> None:
        with self._loops_lock:
            loop = self._loops.pop(client.client_id, None)
        if loop is not None:
            loop.stop()

    def training_step(self, step: int) -> None:
        if hasattr(self, "training_status"):
            self.training_status.content = f"**Training:** showing step {step}"
        for loop in list(self._loops.values()):
            loop.wake.set()

    def stop(self) -> None:
        with self._loops_lock:
            loops = list(self._loops.values())
            self._loops.clear()
        for loop in loops:
            loop.stop()
        for loop in loops:
            loop.join(timeout=10.0)
        self.server.stop()


class _ClientLoop(threading.Thread):
    """Renders for one browser: a low-resolution frame sized to the measured speed while the
    camera moves, the full resolution once it is still (abandoned if it moves again)."""

    def __init__(self, viewer: Viewer, client):
        super().__init__(daemon=True, name=f"viewer-client-{client.client_id}")
        self.viewer, self.client = viewer, client
        self.wake = threading.Event()
        self.running = True
        self.camera_version = 0
        self.moved_at = 0.0
        self.pixels_per_second: float | None = None
        self.rendered_key: tuple | None = None
        self.rendered_at = 0.0
        self.last_image: ViewerImage | None = None
        self._cache: tuple[tuple, Frame] | None = None
        self._render_lock = threading.Lock()

    def camera_moved(self) -> None:
        self.camera_version += 1
        self.moved_at = time.perf_counter()
        self.wake.set()

    def stop(self) -> None:
        self.running = False
        self.wake.set()

    def _full_height(self, aspect: float) -> int:
        longest = int(self.viewer.max_resolution.value)
        return max(MIN_HEIGHT, min(longest, round(longest / aspect)))

    def _height(self, aspect: float, full: bool) -> int:
        full_height = self._full_height(aspect)
        if full or self.pixels_per_second is None:
            return full_height if full else MIN_HEIGHT * 2
        pixels = self.pixels_per_second * MOVING_FRAME_SECONDS
        return max(MIN_HEIGHT, min(full_height, int(math.sqrt(pixels / aspect))))

    def render_once(self, full: bool) -> ViewerImage:
        """Render the browser's current view now (full resolution or the moving size)."""
        viewer, renderer = self.viewer, self.viewer.renderer
        version = self.camera_version
        viewer_camera = viewer_camera_of(self.client)
        height = self._height(viewer_camera.aspect, full)
        snapshot_version = renderer.snapshots.latest().version
        frame_key = (viewer_camera, height, snapshot_version)
        cached = self._cache[1] if self._cache is not None and self._cache[0] == frame_key else None
        cancelled = (lambda: not self.running or self.camera_version != version) if full else None
        output = viewer.output_key()
        with self._render_lock:
            started = time.perf_counter()
            shown = renderer.render(viewer_camera, height, output, float(viewer.ev.value), cached=cached,
                                    cancelled=cancelled)
            seconds = time.perf_counter() - started
        # error maps render the dataset camera, not this one: nothing to re-use or time
        if shown.frame is not None and shown.frame is not cached and output not in ERROR_OUTPUTS:
            self._cache = (frame_key, shown.frame)
            rate = shown.frame.hdr.shape[0] * shown.frame.hdr.shape[1] / max(seconds, 1e-6)
            self.pixels_per_second = rate if self.pixels_per_second is None else 0.5 * (self.pixels_per_second + rate)
        return shown

    def run(self) -> None:
        viewer = self.viewer
        while self.running:
            self.wake.wait(timeout=0.25)
            self.wake.clear()
            if not self.running:
                break
            try:
                self.client.camera.wxyz  # noqa: B018 - raises until the browser has sent its camera
            except AssertionError:
                continue
            moving = time.perf_counter() - self.moved_at < MOVE_SETTLE and bool(viewer.adaptive.value)
            snapshot_version = viewer.renderer.snapshots.latest().version
            key = (self.camera_version, viewer.settings_version, snapshot_version, not moving)
            if key == self.rendered_key:
                continue
            only_model_changed = self.rendered_key is not None and key[:2] == self.rendered_key[:2] \
                and key[3] == self.rendered_key[3]
            if only_model_changed and time.perf_counter() - self.rendered_at < TRAINING_REFRESH:
                continue
            try:
                shown = self.render_once(full=not moving)
            except RenderCancelled:
                continue
            except Exception as error:  # noqa: BLE001 - keep the viewer alive, say what failed
                console.print(f"[red]viewer: render failed: {error}")
                viewer.status.content = f"**Render failed:** {error}"
                self.rendered_key = key
                continue
            if not self.running:
                break
            self.client.scene.set_background_image(shown.image, format="jpeg", jpeg_quality=92 if not moving else 60)
            self.last_image, self.rendered_key, self.rendered_at = shown, key, time.perf_counter()
            height, width = shown.image.shape[:2]
            viewer.status.content = f"{width} x {height} px" + (f" · {shown.note}" if shown.note else "")


def wait_for_interrupt() -> None:
    """Block until Ctrl+C (SIGINT) or SIGTERM; both handled here, so a viewer started where
    SIGINT is ignored (a background job) still stops on it."""
    stop = threading.Event()
    previous = {number: signal.signal(number, lambda *_: stop.set()) for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stop.wait(0.5):
            pass
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def view_command(config: ViewConfig) -> None:
    model = load_model(config.checkpoint)
    snapshots = ModelSnapshots(model.pipeline, model.step, copy_model=False)
    viewer = Viewer(ViewerRenderer(snapshots, model.scene), host=config.host, port=config.port, out=config.out,
                    max_resolution=config.max_resolution)
    console.print(f"[bold]viewer of {config.checkpoint} (step {model.step}) at {viewer.url}[/bold]  (Ctrl+C to stop)")
    try:
        wait_for_interrupt()
    finally:
        viewer.stop()
    console.print("viewer stopped")


def train_with_viewer(trainer, report: Callable[[dict], None]) -> dict:
    """Train while a viewer shows the model (training never waits for it); after training the
    viewer stays open on the final model until Ctrl+C. `report` receives the metrics first."""
    config = trainer.config
    snapshots = ModelSnapshots(trainer.pipeline, trainer.step)
    viewer = Viewer(ViewerRenderer(snapshots, trainer.scene), host=config.viewer_host, port=config.viewer_port,
                    out=config.out / "viewer", training=True)
    console.print(f"[bold]viewer at {viewer.url}[/bold]")
    try:
        metrics = trainer.train(extra_hooks=[SnapshotPublisher(snapshots, viewer.has_clients, viewer.training_step)])
        snapshots.publish(trainer.pipeline, trainer.step)
        viewer.training_step(trainer.step)
        report(metrics)
        console.print(f"[bold]training done; the viewer stays at {viewer.url}[/bold]  (Ctrl+C to stop)")
        wait_for_interrupt()
    finally:
        viewer.stop()
    return metrics
