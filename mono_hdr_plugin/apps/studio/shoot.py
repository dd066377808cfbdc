"""A photographer with a real camera in a studio scene: JPEG files with EXIF, as process-data gets them.

The camera meters every view itself (auto-exposure: the exposure that puts the geometric-mean
luminance at a key value, with some metering jitter, rounded to third stops), adds sensor noise,
saves JPEGs and writes EXIF as a camera does: exposure time, aperture, ISO, 35 mm focal length,
capture time, and ExposureMode (auto, or auto bracket). At some viewpoints it shoots an exposure
bracket around the metered exposure. `exposure_exif=False` leaves the exposure fields out, as a
phone app or an editor that strips them would. The truth (pose, exact exposure and HDR of every
photo) is returned for scoring, never written next to the photos.
"""

import math
from dataclasses import asdict, dataclass, field
from datetime import datetime
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image

from mono_hdr_plugin.apps.studio.capture import capture
from mono_hdr_plugin.apps.studio.render import SceneRender, luminance, render_scene
from mono_hdr_plugin.apps.studio.scene import StudioScene
from mono_hdr_plugin.data.photos.exif import EXPOSURE_MODE_AUTO_BRACKET, make_exif

EXPOSURE_MODE_AUTO = 0
FULL_FRAME_WIDTH_MM = 36.0
START_TIME = datetime(2025, 6, 1, 10, 0, 0).timestamp()


@dataclass(frozen=True)
class ShootConfig:
    """How the simulated photographer works."""

    views: str = "train"
    """Which scene cameras to photograph: train (the scene's training views; its test views are left
    for scoring) or all."""
    bracket_every: int = 4
    """Shoot an exposure bracket at every N-th photographed viewpoint (0: none)."""
    bracket_stops: tuple[float, ...] = (-12.0, -9.0, -6.0, -3.0, 0.0, 3.0)
    """Exposure steps of a bracket around the metered exposure, in stops; a bare bulb needs a deep
    negative end."""
    brightness: float = 32.0
    """The scene is this many times brighter than the studio render's unit of radiance (whose middle
    exposure is 2 s), so the camera meters indoor tripod times around 1/8 s."""
    metering_key: float = 0.18
    """Auto-exposure puts the geometric-mean luminance of the view at this linear value."""
    metering_jitter: float = 0.35
    """Standard deviation, in stops, of the camera's metering error from view to view."""
    exposure_exif: bool = True
    """Write exposure time, aperture, ISO and exposure mode into the EXIF (False: leave them out)."""
    noise: bool = True
    """Add sensor noise (Poisson shot noise and read noise) whether or not the scene declares it."""
    quality: int = 95
    """JPEG quality."""
    iso: int = 100
    f_number: float = 2.8
    seconds_between_views: float = 5.0
    seconds_between_bracket_shots: float = 0.3
    seed: int = 0


@dataclass
class ShotTruth:
    """One photo as it was really taken."""

    file: str
    view: int
    """Index of the scene camera."""
    exposure: float
    """Exposure time in seconds, exactly as photographed (EXIF holds the same value when written);
    the photo is the scene's HDR (radiance times ShootConfig.brightness) times this."""
    bracket: int | None = None
    """Index of the bracket set, None for a single photo."""
    stops: float = 0.0
    """Offset from the metered exposure (0 for single photos and the bracket's metered shot)."""
    seed: int = 0
    """Seed of this photo's sensor noise (studio.capture.capture)."""


@dataclass
class ShootResult:
    """The photos of one shoot and what they really are."""

    folder: Path
    shots: list[ShotTruth]
    held_out: list[int]
    """Scene cameras that were not photographed: left for scoring novel views."""
    config: ShootConfig = field(default_factory=ShootConfig)

    @property
    def bracket_views(self) -> list[int]:
        return sorted({shot.view for shot in self.shots if shot.bracket is not None})

    def to_json(self) -> dict:
        return {
            "folder": str(self.folder),
            "shots": [asdict(shot) for shot in self.shots],
            "held_out": self.held_out,
            "config": asdict(self.config),
        }


def third_stop(seconds: float) -> Fraction:
    """The nearest third-stop exposure time, as the rational a camera writes into EXIF."""
    return Fraction(2 ** (round(3 * math.log2(seconds)) / 3)).limit_denominator(1_000_000)


def metered_exposure(radiance: np.ndarray, key: float) -> float:
    """Seconds that put the geometric-mean luminance of the lit pixels of linear radiance [H, W, 3]
    at `key`. Pixels that see nothing (a render's empty background) do not count: a camera's meter
    reads a dim scene, not a void, and they would drag a geometric mean towards zero."""
    values = luminance(radiance)
    lit = values[values > 0]
    return key / float(np.exp(np.mean(np.log(lit)))) if lit.size else 1.0


def save_jpeg(path: Path, pixels: np.ndarray, quality: int = 95, **exif) -> Path:
    """float [H, W, 3] in [0, 1] -> a JPEG carrying the given EXIF fields (see make_exif)."""
    Image.fromarray((np.clip(pixels, 0, 1) * 255).round().astype(np.uint8)).save(
        path, quality=quality, exif=make_exif(**exif)
    )
    return path


def shoot(
    scene: StudioScene, folder: Path, config: ShootConfig = ShootConfig(), render: SceneRender | None = None
) -> ShootResult:
    """Photograph `scene` into `folder` (created) as IMG_0001.jpg ...; returns the truth of every photo."""
    if config.views not in ("train", "all"):
        raise ValueError(f"views must be train or all, got {config.views!r}")
    if config.bracket_every < 0 or len(set(config.bracket_stops)) < 2 and config.bracket_every:
        raise ValueError("a bracket needs two or more different bracket_stops; bracket_every must be >= 0")
    render = render if render is not None else render_scene(scene)
    cameras = scene.cameras()
    chosen = [i for i in range(len(cameras)) if config.views == "all" or scene.split(i) == "train"]
    effects = tuple(dict.fromkeys(scene.effects + (("noise",) if config.noise else ())))
    focal_35mm = round(cameras[0].fx * FULL_FRAME_WIDTH_MM / max(scene.width, scene.height))
    rng = np.random.default_rng(config.seed)
    folder.mkdir(parents=True, exist_ok=True)
    shots: list[ShotTruth] = []
    clock, brackets = START_TIME, 0
    for position, view in enumerate(chosen):
        radiance = render.radiance[view] * np.float32(config.brightness)
        metered = metered_exposure(radiance, config.metering_key) * 2 ** rng.normal(0, config.metering_jitter)
        bracketed = config.bracket_every > 0 and position % config.bracket_every == 0
        steps = config.bracket_stops if bracketed else (0.0,)
        for step in steps:
            exposure = third_stop(metered * 2**step)
            name, seed = f"IMG_{len(shots) + 1:04d}.jpg", config.seed * 100_003 + len(shots)
            pixels = capture(radiance, float(exposure), effects, scene.capture, seed=seed)
            fields = {
                "exposure": exposure,
                "iso": config.iso,
                "f_number": Fraction(config.f_number).limit_denominator(100),
                "exposure_mode": EXPOSURE_MODE_AUTO_BRACKET if bracketed else EXPOSURE_MODE_AUTO,
            }
            save_jpeg(
                folder / name,
                pixels,
                config.quality,
                focal_35mm=focal_35mm,
                timestamp=clock,
                **(fields if config.exposure_exif else {}),
            )
            shots.append(
                ShotTruth(
                    file=name,
                    view=view,
                    exposure=float(exposure),
                    bracket=brackets if bracketed else None,
                    stops=step,
                    seed=seed,
                )
            )
            clock += config.seconds_between_bracket_shots + float(exposure)
        brackets += bracketed
        clock += config.seconds_between_views
    return ShootResult(
        folder=folder, shots=shots, held_out=[i for i in range(len(cameras)) if i not in chosen], config=config
    )
