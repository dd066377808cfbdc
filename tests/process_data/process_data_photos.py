"""A textured studio scene photographed from known cameras, saved as JPEGs with EXIF.

The built-in scenes are checkerboards, whose repeated corners confuse SIFT matching; this one
wraps multi-scale noise textures on a floor, a wall, a box and a ball under a uniform sky, so
structure from motion finds thousands of distinct features and the render converges quickly.
"""

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image
from PIL.TiffImagePlugin import IFDRational

from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.studio.capture import capture
from mono_hdr_plugin.studio.render import render_scene
from mono_hdr_plugin.studio.scene import CameraRig, StudioScene, box, diffuse, panel, place, rgb, rotate, scale, translate

EXIF_IFD, TAG_MAKE, TAG_MODEL, TAG_ORIENTATION = 0x8769, 0x010F, 0x0110, 0x0112
TAG_EXPOSURE_TIME, TAG_F_NUMBER, TAG_ISO, TAG_FOCAL_35MM = 0x829A, 0x829D, 0x8827, 0xA405


def noise_texture(path: Path, size: int = 512, seed: int = 0) -> Path:
    """A colourful multi-scale noise PNG: blobs at every scale give SIFT features at every distance."""
    rng = np.random.default_rng(seed)
    image = np.zeros((size, size, 3))
    for cells, weight in ((4, 1.0), (16, 0.8), (64, 0.6)):
        grid = rng.random((cells, cells, 3))
        image += weight * np.kron(grid, np.ones((size // cells, size // cells, 1)))
    image = (image - image.min()) / (image.max() - image.min())
    Image.fromarray((image * 255).astype(np.uint8)).save(path)
    return path


def textured_content(texture: Path) -> dict:
    def textured(tiles: float) -> dict:
        return diffuse({"type": "bitmap", "filename": str(texture), "to_uv": scale(tiles, tiles, 1.0)})

    return {
        "floor": panel(scale(2.0), textured(1.0)),
        "wall": panel(place(translate(0, 1.5, 1.0), rotate("x", 90), scale(2.0, 1.0, 1)), textured(0.7)),
        "block": box((-0.6, 0.3, 0.3), (0.6, 0.6, 0.6), textured(0.5)),
        "ball": {"type": "sphere", "center": [0.5, -0.2, 0.35], "radius": 0.35, "bsdf": textured(2.0)},
        "sky": {"type": "constant", "radiance": rgb(1.0)},
    }


def textured_scene(texture: Path, views: int, resolution: int) -> StudioScene:
    return StudioScene(
        name=f"process-data-{views}x{resolution}", description="noise-textured objects under a uniform sky",
        content=lambda: textured_content(texture),
        rig=CameraRig(target=(0.0, 0.3, 0.4), radius=3.2, azimuth_deg=(-150.0, -30.0), elevation_deg=(20.0, 40.0),
                      fov_deg=55.0, views=views),
        resolution=(resolution, resolution), spp=9, max_depth=2)


@dataclass
class PhotoShoot:
    """JPEGs of a studio scene: the folder, the true cameras and exposure of each file."""

    folder: Path
    cameras: list[Camera]
    exposures: list[float]
    names: list[str]


def exif_bytes(exposure: Fraction | None = None, iso: int | None = None, f_number: Fraction | None = None,
               focal_35mm: int | None = None, model: str | None = "StudioCam", orientation: int | None = None):
    exif = Image.Exif()
    if model:
        exif[TAG_MAKE], exif[TAG_MODEL] = "Mono-HDR", model
    if orientation:
        exif[TAG_ORIENTATION] = orientation
    details = exif.get_ifd(EXIF_IFD)
    for tag, value in ((TAG_EXPOSURE_TIME, exposure), (TAG_F_NUMBER, f_number), (TAG_ISO, iso),
                       (TAG_FOCAL_35MM, focal_35mm)):
        if value is not None:  # Pillow writes rationals from IFDRational, not Fraction
            details[tag] = IFDRational(value.numerator, value.denominator) if isinstance(value, Fraction) else value
    return exif


def save_jpeg(path: Path, pixels: np.ndarray, **exif) -> Path:
    """float [H, W, 3] in [0, 1] -> a quality-95 JPEG carrying the given EXIF fields."""
    Image.fromarray((np.clip(pixels, 0, 1) * 255).round().astype(np.uint8)).save(
        path, quality=95, exif=exif_bytes(**exif))
    return path


def shoot(scene: StudioScene, folder: Path, exposures: list[Fraction]) -> PhotoShoot:
    """Render (cached) and photograph view i at exposures[i % len], EXIF as a real camera writes it."""
    render = render_scene(scene)
    cameras = scene.cameras()
    focal_35mm = round(cameras[0].fx * 36.0 / max(scene.width, scene.height))
    folder.mkdir(parents=True, exist_ok=True)
    names, times = [], []
    for index, camera in enumerate(cameras):
        exposure = exposures[index % len(exposures)]
        # The scene's radiance is scaled for exposures around 2 s; photographing at 1.5 s times
        # the ratio to the first EXIF time keeps the photos well exposed whatever EXIF says.
        pixels = capture(render.radiance[index], 1.5 * float(exposure / exposures[0]), scene.effects,
                         scene.capture)
        name = f"IMG_{index + 1:04d}.jpg"
        save_jpeg(folder / name, pixels, exposure=exposure, iso=100, f_number=Fraction(28, 10),
                  focal_35mm=focal_35mm)
        names.append(name)
        times.append(float(exposure))
    return PhotoShoot(folder, cameras, times, names)


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (scale, rotation [3, 3], translation [3]) that best maps points [N, 3] onto target."""
    source_mean, target_mean = source.mean(0), target.mean(0)
    centred_source, centred_target = source - source_mean, target - target_mean
    u, singular, vt = np.linalg.svd(centred_target.T @ centred_source / len(source))
    sign = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:  # a reflection is not a rotation
        sign[2, 2] = -1
    rotation = u @ sign @ vt
    scale_factor = (singular * np.diag(sign)).sum() / (centred_source**2).sum(1).mean()
    return scale_factor, rotation, target_mean - scale_factor * rotation @ source_mean

