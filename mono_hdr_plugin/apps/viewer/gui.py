"""The viser server of the viewer: its controls, and one render thread per connected browser
(`_ClientLoop`) that renders through `ViewerRenderer` (threads: see snapshots.py)."""

import math
import signal
import threading
import time
from pathlib import Path

from rich.console import Console

from mono_hdr_plugin.apps.camera_paths import ViewerCamera, viewer_from_camera
from mono_hdr_plugin.apps.viewer.renderer import ERROR_OUTPUTS, VIEWER_OUTPUTS, ViewerImage, ViewerRenderer, save_view
from mono_hdr_plugin.training.pipeline import Frame, RenderCancelled

console = Console(stderr=True)
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
# While the camera moves, frames aim at this many seconds; it counts as still after MOVE_SETTLE s.
MOVING_FRAME_SECONDS = 0.1
MOVE_SETTLE = 0.3
MIN_HEIGHT = 24
# During training, re-render a still view for a new snapshot at most this often.
TRAINING_REFRESH = 2.0


def viewer_camera_of(client) -> ViewerCamera:
    camera = client.camera
    w, x, y, z = (float(v) for v in camera.wxyz)
    return ViewerCamera(
        wxyz=(w, x, y, z), position=_point(camera.position), fov=float(camera.fov), aspect=float(camera.aspect)
    )


def _point(values) -> tuple[float, float, float]:
    """A position or direction as three floats, the way viser takes them."""
    x, y, z = (float(v) for v in values)
    return x, y, z


class Viewer:
    """The viser server, its controls, and one render thread per connected browser."""

    def __init__(
        self,
        renderer: ViewerRenderer,
        host: str = "127.0.0.1",
        port: int = 7007,
        out: Path = Path("outputs/viewer"),
        max_resolution: int = 512,
        training: bool = False,
    ):
        import viser

        if host not in LOCAL_HOSTS:
            console.print(
                f"[yellow]warning: the viewer listens on {host}: anyone who can reach this machine on the "
                "network can open it (there is no password) and save files into "
                f"{out}. Use the default --host 127.0.0.1 with an SSH tunnel to keep it private."
            )
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
        self.server.scene.set_up_direction(_point(self.renderer.up))
        initial = self.server.initial_camera
        initial.position = start.position
        initial.look_at = _point(self.renderer.focus)
        initial.up = _point(self.renderer.up)
        initial.fov = start.fov

    def _add_controls(self, max_resolution: int, training: bool) -> None:
        gui = self.server.gui
        gui.configure_theme(dark_mode=True, show_share_button=False)
        self.status = gui.add_markdown("")
        if training:
            self.training_status = gui.add_markdown("**Training:** waiting for the first snapshot")
        with gui.add_folder("Exposure"):
            self.ev = gui.add_slider(
                "EV (stops)",
                min=-10.0,
                max=10.0,
                step=0.1,
                initial_value=0.0,
                hint="Stops from the training exposure: +1 doubles the exposure time",
            )
            self.exposure_time = gui.add_number(
                "Exposure (s)",
                initial_value=1.0,
                min=1e-9,
                step=1e-4,
                hint="Exposure time in seconds (same control as EV)",
            )
            reset = gui.add_button("Training exposure")
        with gui.add_folder("Output"):
            self.output = gui.add_dropdown("Show", tuple(VIEWER_OUTPUTS.values()), initial_value=VIEWER_OUTPUTS["ldr"])
        with gui.add_folder("Camera"):
            self.view_choice = gui.add_dropdown("Dataset camera", tuple(self.renderer.views))
            go = gui.add_button("Go to camera")
        with gui.add_folder("Resolution"):
            self.max_resolution = gui.add_slider(
                "Longest side (px)", min=64, max=2048, step=16, initial_value=max(64, min(2048, max_resolution))
            )
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
            # viser's value setter is invisible to mypy (a method sits between it and the getter)
            self.exposure_time.value = float(f"{model.exposure_at(self.ev.value):.6g}")  # type: ignore[misc]
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
                self.ev.value = round(min(10.0, max(-10.0, ev)), 1)  # type: ignore[misc]  # viser's setter, as above
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
            if shown.frame is None:  # the view became an error map away from a dataset camera since the check
                raise ValueError("the view has no rendered frame now; go back to the view and save again")
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
            shown = renderer.render(
                viewer_camera, height, output, float(viewer.ev.value), cached=cached, cancelled=cancelled
            )
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
            only_model_changed = (
                self.rendered_key is not None and key[:2] == self.rendered_key[:2] and key[3] == self.rendered_key[3]
            )
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
