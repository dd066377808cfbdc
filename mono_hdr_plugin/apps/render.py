"""`mono-hdr render`: a trained model's test views as EXR + PNG, camera-path videos with EXR
sequences for compositing, and exposure sweeps (video + strip) at a fixed view."""

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Literal

import imageio.v2 as imageio
import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from mono_hdr_plugin.apps.camera_paths import PathKind, camera_path
from mono_hdr_plugin.apps.display import OUTPUTS, Output, needs_render_at, to_display, to_uint8
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.validation import ANY_FINITE, NON_NEGATIVE, POSITIVE, FlagError, at_least
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.data.io import atomic_path, write_exr, write_png
from mono_hdr_plugin.training.evaluation import first_per_camera, save_hdr_renders
from mono_hdr_plugin.training.pipeline import Frame
from mono_hdr_plugin.training.trained import TrainedModel, load_trained_model

console = Console(stderr=True)


@dataclass
class RenderConfig:
    """Render a checkpoint: test views (EXR, PNGs), a camera-path video (--path) or an exposure sweep (--sweep).

    Test views: <view>_hdr.exr, <view>_hdr_mulaw.png, <view>_ldr_<t>s.png and <view>_ev_sheet.png
    (the held-out photo beside the render at --sheet-evs stops from its exposure) in OUT."""

    checkpoint: Path
    """A checkpoint written by `mono-hdr train`."""
    out: Path = Path("outputs/render")
    """Folder for the images (and the default place of videos and strips)."""
    exposures: tuple[float, ...] = ()
    """Test views: exposure times in seconds for LDR PNGs (default: the training exposures).
    Baselines use their learned CRF; Mono-HDR's LDR branch exists at its training exposure only,
    so other exposures are shown as the HDR render through the sRGB display curve."""
    max_views: int | None = None
    """Test views: render at most this many."""
    sheet_evs: tuple[float, ...] = (-4.0, -2.0, 0.0, 2.0, 4.0)
    """Test views: the stops, from each view's own exposure, of its EV sheet (the photo, then the
    render at each; EV 0 is the photo's exposure). --sheet-evs with no value: no sheet."""
    path: PathKind | None = None
    """Render a camera path instead of the test views: dataset (the split's cameras), interpolate
    (a glide through them), spiral (around the scene's focus point)."""
    frames: int | None = None
    """Frames of the path (default: every dataset camera, 120 otherwise) or of the sweep (default 13)."""
    split: Literal["train", "test"] = "test"
    """Cameras the path goes through."""
    video: Path | None = None
    """MP4 to write (H.264, imageio-ffmpeg); default OUT/path_<path>.mp4 or OUT/exposure_sweep.mp4."""
    fps: int = 24
    """Frames per second of the video."""
    exr_frames: Path | None = None
    """Also write each path frame's linear HDR as DIR/frame_00000_hdr.exr (for compositing)."""
    output: Output = "ldr"
    """What the video shows: ldr, hdr-srgb, hdr-filmic, hdr-mulaw or depth (see docs/viewer.md)."""
    ev: float = 0.0
    """Path videos: exposure in stops relative to the training exposure."""
    scale: float = 1.0
    """Resolution of path and sweep frames relative to the dataset cameras."""
    sweep: bool = False
    """Render an exposure sweep at one view (--view) from --ev-min to --ev-max: a video and a strip PNG."""
    view: int = 0
    """Sweep: index of the view among the split's cameras."""
    ev_min: float = -6.0
    """Sweep: first exposure, in stops relative to the training exposure."""
    ev_max: float = 6.0
    """Sweep: last exposure, in stops relative to the training exposure."""
    strip: Path | None = None
    """Sweep: strip PNG of every frame side by side with its EV; default OUT/exposure_sweep.png."""

    flag_rules: ClassVar = {
        "exposures": POSITIVE,
        "max_views": at_least(1),
        "frames": at_least(1),
        "fps": at_least(1),
        "ev": ANY_FINITE,
        "scale": POSITIVE,
        "view": NON_NEGATIVE,
        "ev_min": ANY_FINITE,
        "ev_max": ANY_FINITE,
        "sheet_evs": ANY_FINITE,
    }


def progress_bar() -> Progress:
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
    )


VIDEO_SUFFIXES = (".mp4", ".mkv", ".mov")
"""Containers that hold the H.264 stream write_video makes (imageio picks its writer by the suffix)."""
# The renders each flag shapes: a flag given for another render would be ignored without a word.
FLAG_RENDERS = {
    "exposures": ("views",),
    "max_views": ("views",),
    "sheet_evs": ("views",),
    "frames": ("path", "sweep"),
    "split": ("path", "sweep"),
    "video": ("path", "sweep"),
    "fps": ("path", "sweep"),
    "output": ("path", "sweep"),
    "scale": ("path", "sweep"),
    "exr_frames": ("path",),
    "ev": ("path",),
    "view": ("sweep",),
    "ev_min": ("sweep",),
    "ev_max": ("sweep",),
    "strip": ("sweep",),
}
RENDER_FLAGS = {
    "views": "test-view renders (no --path or --sweep)",
    "path": "--path renders",
    "sweep": "--sweep renders",
}


def check_render_flags(config: RenderConfig) -> None:
    """Refuse, before the (slow) checkpoint load, a flag of another kind of render and an output file
    whose suffix would not get what its flag writes, naming the flag."""
    if config.path is not None and config.sweep:
        raise FlagError("--path and --sweep are two different renders: give one of them")
    kind = "path" if config.path is not None else "sweep" if config.sweep else "views"
    defaults = RenderConfig(checkpoint=config.checkpoint)
    for name, renders in FLAG_RENDERS.items():
        if kind not in renders and getattr(config, name) != getattr(defaults, name):
            flag = "--" + name.replace("_", "-")
            wanted = " and ".join(RENDER_FLAGS[render] for render in renders)
            raise FlagError(f"{flag} applies to {wanted} only, not to {RENDER_FLAGS[kind]}: leave {flag} out")
    if config.video is not None and config.video.suffix.lower() not in VIDEO_SUFFIXES:
        raise FlagError(f"--video must name a {', '.join(VIDEO_SUFFIXES)} file (H.264), got {config.video}")
    if config.strip is not None and config.strip.suffix.lower() != ".png":
        raise FlagError(f"--strip must name a .png file, got {config.strip}")
    if config.exr_frames is not None and config.exr_frames.is_file():
        raise FlagError(
            f"--exr-frames must name a folder (frames are written into it), got the file {config.exr_frames}"
        )


def render_command(config: RenderConfig) -> None:
    """`mono-hdr render` with flags check_render_flags accepted."""
    if config.path is None and not config.sweep:
        written = render_checkpoint(
            config.checkpoint, config.out, config.exposures, config.max_views, sheet_evs=config.sheet_evs
        )
        console.print(f"wrote {len(written)} images to {config.out}")
        return
    model = load_trained_model(config.checkpoint)
    views = model.scene.test if config.split == "test" and model.scene.test else model.scene.train
    if config.path is not None:
        video = config.video or config.out / f"path_{config.path}.mp4"
        cameras = [
            even_sized(c.scaled(config.scale) if config.scale != 1 else c)
            for c in camera_path(config.path, model.scene, views, config.frames)
        ]
        render_path(
            model, cameras, video, output=config.output, ev=config.ev, fps=config.fps, exr_folder=config.exr_frames
        )
        console.print(
            f"wrote {len(cameras)} frames to {video}" + (f" and {config.exr_frames}" if config.exr_frames else "")
        )
        return
    choices = first_per_camera(views)
    if not 0 <= config.view < len(choices):
        raise ValueError(f"--view {config.view} is out of range: the {config.split} split has {len(choices)} cameras")
    camera = choices[config.view].camera
    camera = even_sized(camera.scaled(config.scale) if config.scale != 1 else camera)
    evs = np.linspace(config.ev_min, config.ev_max, config.frames or 13).tolist()
    video = config.video or config.out / "exposure_sweep.mp4"
    strip = config.strip or config.out / "exposure_sweep.png"
    render_exposure_sweep(model, camera, evs, video, strip, output=config.output, fps=config.fps)
    console.print(f"wrote the sweep EV {config.ev_min:+g} to {config.ev_max:+g} to {video} and {strip}")


def even_sized(camera: Camera) -> Camera:
    """The camera cropped by one pixel where its width or height is odd (H.264 needs even sizes)."""
    width, height = camera.width - camera.width % 2, camera.height - camera.height % 2
    if (width, height) == (camera.width, camera.height):
        return camera
    if width == 0 or height == 0:
        raise ValueError(f"frames of {camera.width} x {camera.height} pixels are too small for a video: raise --scale")
    return Camera(
        c2w=camera.c2w,
        fx=camera.fx,
        fy=camera.fy,
        cx=camera.cx,
        cy=camera.cy,
        width=width,
        height=height,
        near=camera.near,
        far=camera.far,
    )


def display_frame(
    model: TrainedModel, camera: Camera, output: str, exposure: float, cached: Frame | None = None
) -> tuple[Frame, np.ndarray]:
    """A frame of `camera` (re-used from `cached` when the output does not need a new render)
    and its uint8 display image."""
    if output not in OUTPUTS:
        raise ValueError(f"unknown --output {output!r}; choose one of {', '.join(OUTPUTS)}")
    frame = cached
    if frame is None or (needs_render_at(output, model.exposure) and frame.exposure != exposure):
        frame = model.pipeline.render(
            camera,
            exposure if needs_render_at(output, model.exposure) else model.exposure.reference_exposure,
            with_depth=output == "depth",
        )
    return frame, to_uint8(to_display(frame, output, exposure, model.exposure))


def write_video(path: Path, frames, fps: int) -> None:
    """Write uint8 frames [H, W, 3] as H.264 MP4 at their own size, atomically."""
    with atomic_path(path) as temporary:
        # macro_block_size=1: keep the frame size (imageio-ffmpeg would otherwise resize to multiples of 16)
        writer = imageio.get_writer(
            temporary,
            fps=fps,
            codec="libx264",
            quality=8,
            macro_block_size=1,
            pixelformat="yuv420p",
            ffmpeg_log_level="error",
        )
        with writer:  # imageio's stub types `with ... as` as the base class, which has no append_data
            for frame in frames:
                writer.append_data(frame)


def render_path(
    model: TrainedModel,
    cameras: list[Camera],
    video: Path,
    output: str = "ldr",
    ev: float = 0.0,
    fps: int = 24,
    exr_folder: Path | None = None,
) -> None:
    """Render `cameras` into `video` (and their linear HDR into exr_folder/frame_NNNNN_hdr.exr)."""
    exposure = model.exposure.exposure_at(ev)

    def frames():
        with progress_bar() as progress:
            task = progress.add_task(f"path ({output})", total=len(cameras))
            for index, camera in enumerate(cameras):
                frame, image = display_frame(model, camera, output, exposure)
                if exr_folder is not None:
                    write_exr(exr_folder / f"frame_{index:05d}_hdr.exr", frame.hdr.float().numpy())
                progress.advance(task)
                yield image

    write_video(video, frames(), fps)


def render_exposure_sweep(
    model: TrainedModel, camera: Camera, evs: list[float], video: Path, strip: Path, output: str = "ldr", fps: int = 6
) -> list[np.ndarray]:
    """One view at each EV in `evs`: an MP4 and a strip PNG (frames side by side, EV below each).
    Returns the uint8 frames."""
    images, frame = [], None
    with progress_bar() as progress:
        task = progress.add_task(f"exposure sweep ({output})", total=len(evs))
        for ev in evs:
            frame, image = display_frame(model, camera, output, model.exposure.exposure_at(ev), cached=frame)
            images.append(image)
            progress.advance(task)
    write_video(video, images, fps)
    write_png(strip, labelled_strip(images, [ev_labels(ev) for ev in evs]).astype(np.float32) / 255.0)
    return images


def ev_labels(ev: float) -> tuple[str, ...]:
    """A frame's label, longest first: `EV +2`, else `+2` where the frame is too narrow."""
    return (f"EV {ev:+g}", f"{ev:+g}")


def labelled_strip(images: list[np.ndarray], labels: list[tuple[str, ...]], label_height: int = 14) -> np.ndarray:
    """uint8 [H + label, N * (W + gap) - gap, 3]: the frames in a row, each with the longest of its
    labels that fits beneath it (the last one where none does)."""
    height, width = images[0].shape[:2]
    gap = 2
    canvas = Image.new("RGB", (len(images) * (width + gap) - gap, height + label_height), (255, 255, 255))
    draw, font = ImageDraw.Draw(canvas), ImageFont.load_default()
    for index, (image, choices) in enumerate(zip(images, labels, strict=True)):
        left = index * (width + gap)
        canvas.paste(Image.fromarray(image), (left, 0))
        label = next((text for text in choices if draw.textlength(text, font=font) <= width - 2), choices[-1])
        draw.text((left + width / 2, height + label_height / 2), label, fill=(0, 0, 0), font=font, anchor="mm")
    return np.asarray(canvas)


def ev_sheet(model: TrainedModel, view: View, evs: tuple[float, ...]) -> np.ndarray:
    """uint8 strip: held-out `view`'s photo, then the model's render of its camera at each of `evs`
    stops from the photo's own exposure (so the EV 0 frame is the model's version of the photo)."""
    images, frame = [to_uint8(view.image)], None
    for ev in evs:
        frame, image = display_frame(model, view.camera, "ldr", view.exposure * 2.0**ev, cached=frame)
        images.append(image)
    return labelled_strip(images, [("photo",), *(ev_labels(ev) for ev in evs)])


@torch.no_grad()
def render_checkpoint(
    checkpoint: Path,
    out: Path,
    exposures: tuple[float, ...] = (),
    max_views: int | None = None,
    scene: SceneData | None = None,
    sheet_evs: tuple[float, ...] = (),
) -> list[Path]:
    """Write <view>_hdr.exr, <view>_hdr_mulaw.png, <view>_ldr_<t>s.png and, with `sheet_evs`,
    <view>_ev_sheet.png (`ev_sheet`) for each test view of the checkpoint's own data (or of
    `scene`, an in-memory scene)."""
    for exposure in exposures:
        if not exposure > 0:
            raise ValueError(f"--exposures must be positive seconds, got {exposure}")
    model = load_trained_model(checkpoint, scene=scene)
    exposures = exposures or tuple(model.scene.train_exposures)
    written = []
    for view in first_per_camera(model.scene.test)[:max_views]:
        frame = model.pipeline.render(view.camera, model.exposure.reference_exposure)
        written += save_hdr_renders(out, view, frame.hdr)
        for exposure in exposures:
            frame, ldr = display_frame(model, view.camera, "ldr", exposure, cached=frame)
            written.append(out / f"{view.stem}_ldr_{exposure:g}s.png")
            write_png(written[-1], ldr.astype(np.float32) / 255.0)
        if sheet_evs:
            written.append(out / f"{view.stem}_ev_sheet.png")
            write_png(written[-1], ev_sheet(model, view, sheet_evs).astype(np.float32) / 255.0)
    return written
