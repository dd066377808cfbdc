"""A textured studio scene photographed from known cameras, saved as JPEGs with EXIF.

Most built-in scenes are checkerboards, whose repeated corners confuse SIFT matching; this one
wraps the studio's noise texture (a PNG file, as a user's scene would load it) on a floor, a wall,
a box and a ball under a uniform sky, so structure from motion finds thousands of distinct
features and the render converges quickly.
"""

from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np
from PIL import Image

from mono_hdr_plugin.apps.studio.capture import capture
from mono_hdr_plugin.apps.studio.render import render_scene
from mono_hdr_plugin.apps.studio.scene import (
    CameraRig,
    StudioScene,
    box,
    diffuse,
    noise_image,
    panel,
    place,
    rgb,
    rotate,
    scale,
    translate,
)
from mono_hdr_plugin.apps.studio.shoot import save_jpeg
from mono_hdr_plugin.core.cameras import Camera


def noise_texture(path: Path, size: int = 512, seed: int = 0) -> Path:
    """The studio's noise texture (colourful blobs at every scale) as a PNG."""
    Image.fromarray((noise_image(seed, size) * 255).astype(np.uint8)).save(path)
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


def textured_scene(
    texture: Path,
    views: int,
    resolution: int | tuple[int, int],
    azimuth_deg: tuple[float, float] = (-150.0, -30.0),
    fov_deg: float = 55.0,
) -> StudioScene:
    """The textured objects on an arc of `views` cameras; `resolution` is square or (width, height)."""
    width, height = (resolution, resolution) if isinstance(resolution, int) else resolution
    return StudioScene(
        name=f"process-data-{views}x{width}x{height}-{azimuth_deg[0]:g}-{fov_deg:g}",
        description="noise-textured objects under a uniform sky",
        content=lambda: textured_content(texture),
        rig=CameraRig(
            target=(0.0, 0.3, 0.4),
            radius=3.2,
            azimuth_deg=azimuth_deg,
            elevation_deg=(20.0, 40.0),
            fov_deg=fov_deg,
            views=views,
        ),
        resolution=(width, height),
        spp=9,
        max_depth=2,
    )


@dataclass
class PhotoShoot:
    """JPEGs of a studio scene: the folder, the true cameras and exposure of each file."""

    folder: Path
    cameras: list[Camera]
    exposures: list[float]
    names: list[str]


def shoot(scene: StudioScene, folder: Path, exposures: list[Fraction], first_number: int = 1) -> PhotoShoot:
    """Render (cached) and photograph view i at exposures[i % len], EXIF as a real camera writes it,
    as IMG_<first_number + i>.jpg."""
    render = render_scene(scene)
    cameras = scene.cameras()
    focal_35mm = round(cameras[0].fx * 36.0 / max(scene.width, scene.height))
    folder.mkdir(parents=True, exist_ok=True)
    names, times = [], []
    for index in range(len(cameras)):
        exposure = exposures[index % len(exposures)]
        # The scene's radiance is scaled for exposures around 2 s; photographing at 1.5 s times
        # the ratio to the first EXIF time keeps the photos well exposed whatever EXIF says.
        pixels = capture(render.radiance[index], 1.5 * float(exposure / exposures[0]), scene.effects, scene.capture)
        name = f"IMG_{index + first_number:04d}.jpg"
        save_jpeg(folder / name, pixels, exposure=exposure, iso=100, f_number=Fraction(28, 10), focal_35mm=focal_35mm)
        names.append(name)
        times.append(float(exposure))
    return PhotoShoot(folder, cameras, times, names)
