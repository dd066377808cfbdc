"""Render studio scenes with Mitsuba 3, cached on disk by a hash of everything that shapes them.

The `scalar_rgb` variant is used: it needs no system package. `llvm_ad_rgb` is faster where
it works, but on this project's machines its LLVM backend aborts the whole process
("LLVM ERROR: Cannot select"), which cannot be caught; set MONO_HDR_MITSUBA_VARIANT to try it.

Ground truth must not be the limit of what a model can score, so every view is rendered twice
with different seeds: the two must agree (PSNR of the mu-law HDR and of the noise-free photo at
the middle exposure, stored with the render and listed by `mono-hdr scenes`), and their mean is
the ground truth, cleaner still. Orthogonal-array sampling converges several times faster
than independent or stratified samples on these direct-lit scenes.
"""

import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_hdr_plugin.apps.studio.scene import StudioScene
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.progress import PlainProgressLines, duration_text
from mono_hdr_plugin.data.io import atomic_path, write_json

RENDER_VERSION = 2
"""Bump when the rendering code changes what a cached render holds."""
SAMPLER = "orthogonal"
"""Mitsuba sampler of the radiance renders; it takes sample counts that are squares of primes."""

# Mitsuba's sensor looks along +z with +y up and +x to the left; OpenCV has +x right and +y
# down, so flipping x and y maps one onto the other.
OPENCV_TO_MITSUBA = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass
class SceneRender:
    """All views of a scene: linear radiance and the surface point seen by each pixel.

    radiance: [V, H, W, 3] float32, scaled so the middle exposure maps the median of the lit
        pixels to the scene's key value (the HDR ground truth: the mean of two renders).
    positions: [V, H, W, 3] world points. hit: [V, H, W] bool, whether the pixel sees a surface.
    agreement_hdr, agreement_ldr: [V] PSNR (dB) between the two renders of each view, mu-law HDR
        (own max) and the noise-free photo at the middle exposure; inf where they are identical.
    """

    radiance: np.ndarray
    positions: np.ndarray
    hit: np.ndarray
    agreement_hdr: np.ndarray
    agreement_ldr: np.ndarray


def cache_dir() -> Path:
    """$MONO_HDR_CACHE, or ~/.cache/mono-hdr-3d."""
    return Path(os.environ.get("MONO_HDR_CACHE", Path.home() / ".cache" / "mono-hdr-3d"))


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return np.round(value, 9).tolist()
    if isinstance(value, dict):
        return {key: _jsonable(item) for key, item in sorted(value.items())}
    if isinstance(value, (list, tuple)):
        return [_jsonable(item) for item in value]
    return value


def render_key(scene: StudioScene) -> str:
    """Hash of the scene content, cameras, resolution, sample count and render settings."""
    poses = np.stack([c.c2w.numpy() for c in scene.cameras()])
    description = {
        "content": _jsonable(scene.content()),
        "poses": _jsonable(poses),
        "fov": scene.rig.fov_deg,
        "resolution": scene.resolution,
        "spp": scene.spp,
        "max_depth": scene.max_depth,
        "key": scene.key_value,
        "exposures": scene.exposures,
        "version": RENDER_VERSION,
    }
    return hashlib.sha256(json.dumps(description, sort_keys=True).encode()).hexdigest()[:16]


def _mitsuba():
    import mitsuba

    variant = os.environ.get("MONO_HDR_MITSUBA_VARIANT", "scalar_rgb")
    if mitsuba.variant() != variant:
        mitsuba.set_variant(variant)
        # Projector and sky textures are HDR on purpose: Mitsuba's "exceeds [0, 1]" warnings are noise.
        mitsuba.set_log_level(mitsuba.LogLevel.Error)
    return mitsuba


def _to_mitsuba(value, mitsuba):
    """Replace the numpy arrays of a scene dict: [4, 4] matrices by Mitsuba transforms, [H, W, 3]
    images by Mitsuba bitmaps."""
    if isinstance(value, np.ndarray):
        if value.ndim == 3:
            return mitsuba.Bitmap(np.ascontiguousarray(value, np.float32))
        return mitsuba.ScalarTransform4f(value.tolist())
    if isinstance(value, dict):
        return {key: _to_mitsuba(item, mitsuba) for key, item in value.items()}
    return value


def mitsuba_sensor(camera: Camera, spp: int, mitsuba, sampler: str = SAMPLER) -> dict:
    """A Mitsuba perspective sensor that sees exactly what the OpenCV `camera` sees."""
    fov_x = np.degrees(2 * np.arctan(0.5 * camera.width / camera.fx))
    to_world = camera.c2w.double().numpy() @ OPENCV_TO_MITSUBA
    return {
        "type": "perspective",
        "fov": float(fov_x),
        "fov_axis": "x",
        "to_world": mitsuba.ScalarTransform4f(to_world.tolist()),
        "film": {
            "type": "hdrfilm",
            "width": camera.width,
            "height": camera.height,
            "rfilter": {"type": "box"},
            "pixel_format": "rgb",
        },
        "sampler": {"type": sampler, "sample_count": spp},
    }


def _render_view(content: dict, camera: Camera, scene: StudioScene, mitsuba, seed: int) -> np.ndarray:
    """Radiance [H, W, 3] of one view with `scene.spp` samples per pixel."""
    shading = mitsuba.load_dict(
        {
            "type": "scene",
            **content,
            "integrator": {"type": "path", "max_depth": scene.max_depth},
            "sensor": mitsuba_sensor(camera, scene.spp, mitsuba),
        }
    )
    return np.array(mitsuba.render(shading, seed=seed), dtype=np.float32)[..., :3]


def _render_geometry(content: dict, camera: Camera, mitsuba) -> tuple[np.ndarray, np.ndarray]:
    """(positions [H, W, 3], hit [H, W]) of one view: the surface point at each pixel centre."""
    geometry = mitsuba.load_dict(
        {
            "type": "scene",
            **content,
            "integrator": {"type": "aov", "aovs": "pp:position,dd:depth"},
            "sensor": mitsuba_sensor(camera, 1, mitsuba, sampler="independent"),
        }
    )
    aov = np.array(mitsuba.render(geometry, seed=0), dtype=np.float32)
    return aov[..., :3], aov[..., 3] > 0


def radiance_scale(radiance: np.ndarray, scene: StudioScene) -> float:
    """Factor that makes the middle exposure map the median luminance of the lit pixels (a black
    background does not count) to the key value."""
    values = luminance(radiance)
    lit = values[values > 0]
    median = float(np.median(lit)) if lit.size else 0.0
    middle_exposure = sorted(scene.exposures)[len(scene.exposures) // 2]
    return scene.key_value / (middle_exposure * max(median, 1e-12))


def luminance(radiance: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB [..., 3]."""
    return radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)


DEMO_SAMPLE_SECONDS = 20.2 * 60 / (35 * 512 * 512 * 121)
"""Seconds per pixel and sample of a view of demo on 2 cores (its 35 views at 512 x 512 x 121 spp took
20.2 minutes, alone on the machine): the guess for a scene never rendered on this machine. Path
tracing costs about the same per sample, but scenes still differ by their geometry and lights."""


def render_times_path() -> Path:
    return cache_dir() / "studio" / "render-times.json"


def _render_times() -> dict:
    """Seconds per pixel and sample of a view, per scene, measured on this machine ({} if none; a
    damaged file only costs the estimate)."""
    path = render_times_path()
    try:
        times = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        return {}
    return times if isinstance(times, dict) else {}


def measured_view_seconds(scene: StudioScene) -> float | None:
    """Seconds one view of `scene` takes at its size and spp, from this machine's last render of it at
    any size; None if it was never rendered here."""
    rate = _render_times().get(scene.name)
    if not isinstance(rate, (int, float)):
        return None
    return float(rate) * scene.width * scene.height * scene.spp


def record_view_seconds(scene: StudioScene, view_seconds: float) -> None:
    times = _render_times()
    times[scene.name] = view_seconds / (scene.width * scene.height * scene.spp)
    write_json(render_times_path(), times)


def render_minutes(scene: StudioScene) -> tuple[float, bool]:
    """About how long rendering every view of `scene` takes on this machine, and whether that was
    measured here before (else it is a guess at demo's rate per sample)."""
    view = measured_view_seconds(scene)
    measured = view is not None
    if view is None:
        view = DEMO_SAMPLE_SECONDS * scene.width * scene.height * scene.spp
    return view * len(scene.cameras()) / 60, measured


def render_time_text(scene: StudioScene) -> str:
    """The notice's estimate, saying whether it was measured or is a guess."""
    minutes, measured = render_minutes(scene)
    if not measured:
        return f"{about_minutes(minutes)} at demo's rate per sample (a guess until the second view is timed)"
    return f"{about_minutes(minutes)}, at the rate measured here before"


def about_minutes(minutes: float) -> str:
    return f"about {duration_text(minutes * 60)}"


def render_cache_path(scene: StudioScene) -> Path:
    return cache_dir() / "studio" / f"{scene.name}-{render_key(scene)}.npz"


def render_scene(scene: StudioScene, use_cache: bool = True) -> SceneRender:
    """Every view of `scene`, from the cache when the same render was done before; a new render says
    first, in a plain line, what it does and for how long (a progress bar follows in a terminal)."""
    path = render_cache_path(scene)
    if use_cache and path.is_file():
        with np.load(path) as cached:
            return SceneRender(**{name: cached[name] for name in SceneRender.__dataclass_fields__})
    from rich.console import Console

    console = Console(stderr=True, soft_wrap=True)
    cameras = scene.cameras()
    console.print(
        f"rendering studio scene {scene.name} at {scene.width}x{scene.height} with Mitsuba ({len(cameras)} views x 2 "
        f"x {scene.spp} spp, {render_time_text(scene)})"
        + (f"; cached in {path.parent} for next time" if use_cache else ""),
        markup=False,
        highlight=False,
    )
    first_views, second_views, positions, hit, view_seconds = _render_views(scene, cameras, console)
    if use_cache and len(view_seconds) > 1:
        record_view_seconds(scene, float(np.mean(view_seconds[1:])))
    first, second = np.stack(first_views), np.stack(second_views)
    scale = np.float32(radiance_scale(0.5 * (first + second), scene))
    first, second = first * scale, second * scale
    hdr_agreement, ldr_agreement = seed_agreement(first, second, scene)
    render = SceneRender(0.5 * (first + second), np.stack(positions), np.stack(hit), hdr_agreement, ldr_agreement)
    if use_cache:
        with atomic_path(path) as temporary, open(temporary, "wb") as handle:
            np.savez(handle, **{name: getattr(render, name) for name in SceneRender.__dataclass_fields__})
    return render


def _render_views(scene: StudioScene, cameras: list[Camera], console) -> tuple[list, list, list, list, list[float]]:
    """Two radiance renders (two seeds), the surface points and coverage of every view, and each view's
    seconds. Says the time left after the second view (the first also pays Mitsuba's set-up), then, where
    the output is not a terminal, every LOG_EVERY_SECONDS (core/progress.py); a terminal gets a
    progress bar."""
    from rich.progress import Progress

    mitsuba = _mitsuba()
    content = _to_mitsuba(scene.content(), mitsuba)
    first_views, second_views, positions, hit, view_seconds = [], [], [], [], []
    plain_lines = PlainProgressLines(console)
    with Progress(console=console, transient=True) as progress:
        task = progress.add_task(
            f"rendering {scene.name} ({len(cameras)} views x 2 x {scene.spp} spp)", total=len(cameras)
        )
        for index, camera in enumerate(cameras):
            started = time.perf_counter()
            first_views.append(_render_view(content, camera, scene, mitsuba, seed=2 * index))
            second_views.append(_render_view(content, camera, scene, mitsuba, seed=2 * index + 1))
            position, visible = _render_geometry(content, camera, mitsuba)
            positions.append(position)
            hit.append(visible)
            view_seconds.append(time.perf_counter() - started)
            progress.advance(task)
            if 1 <= index < len(cameras) - 1:
                left = float(np.mean(view_seconds[1:])) * (len(cameras) - index - 1) / 60
                plain_lines.print(
                    f"{scene.name}: {index + 1} of {len(cameras)} views, {about_minutes(left)} left", always=index == 1
                )
    return first_views, second_views, positions, hit, view_seconds


def seed_agreement(first: np.ndarray, second: np.ndarray, scene: StudioScene) -> tuple[np.ndarray, np.ndarray]:
    """Per view, PSNR (dB) between two renders [V, H, W, 3]: of their mu-law HDR (each divided by
    its own max) and of their photos at the middle exposure without sensor noise (noise is a
    property of the photo, not of the render)."""
    import torch

    from mono_hdr_plugin.apps.studio.capture import capture
    from mono_hdr_plugin.core.metrics import normalise_hdr, psnr

    middle = sorted(scene.exposures)[len(scene.exposures) // 2]
    effects = tuple(effect for effect in scene.effects if effect != "noise")
    hdr, ldr = [], []
    for a, b in zip(first, second):
        hdr.append(psnr(normalise_hdr(torch.from_numpy(a)), normalise_hdr(torch.from_numpy(b))))
        photo_a, photo_b = (torch.from_numpy(capture(x, middle, effects, scene.capture)) for x in (a, b))
        ldr.append(psnr(photo_a, photo_b))
    return np.asarray(hdr), np.asarray(ldr)


def dynamic_range(radiance: np.ndarray, dark_percentile: float = 1.0) -> float:
    """Brightest pixel luminance over the darkest lit surface (a low percentile of lit pixels).

    A low percentile rather than the minimum, so a few Monte Carlo outliers do not decide it.
    """
    values = luminance(radiance).ravel()
    lit = values[values > 0]
    return float(values.max() / np.percentile(lit, dark_percentile)) if lit.size else 0.0
