"""Outdoor studio scenes: an open sky at infinity (Mitsuba's `envmap` from a numpy lat-long map)
with a small, very bright sun, a textured ground and dark objects, seen from forward-facing arcs.

Mitsuba's lat-long map lives in a local frame with +y up: texel (u, v) is the local direction
(sin(pi v) sin(2 pi u), cos(pi v), -sin(pi v) cos(2 pi u)). ENVMAP_TO_WORLD turns local +y into
world +z, so the map's top row is the zenith and its middle row the horizon.
"""

import math

import numpy as np

from mono_hdr_plugin.apps.studio.capture import CaptureSettings
from mono_hdr_plugin.apps.studio.scene import (
    CameraRig,
    StudioScene,
    box,
    diffuse,
    noise_texture,
    panel,
    place,
    rgb,
    rotate,
    scale,
    translate,
)

ENVMAP_TO_WORLD = rotate("x", 90)
"""Local (x, y, z) -> world (x, -z, y): the map's +y up becomes world +z up."""
SKY_MAP_SIZE = (1024, 512)
"""Width, height of the lat-long sky: 0.35 degrees a texel, so a 1.5 degree sun spans four."""
SUN_RADIUS_DEG = 0.75
"""Half the sun's angular diameter (the real sun's is 0.27); at 128 px and 60 degrees of view it is
about three pixels across."""


def direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """World unit vector (z up) at an azimuth from +x towards +y and an elevation above the ground."""
    azimuth, elevation = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array(
        [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
    )


def sky_directions(size: tuple[int, int] = SKY_MAP_SIZE) -> np.ndarray:
    """[H, W, 3] world directions of the texel centres of a lat-long map placed by ENVMAP_TO_WORLD."""
    width, height = size
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    theta, phi = np.pi * v[:, None], 2 * np.pi * u[None, :]
    local = np.stack(np.broadcast_arrays(np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)), -1)
    return local @ ENVMAP_TO_WORLD[:3, :3].T


def sun_disc(directions: np.ndarray, sun: np.ndarray, radiance, radius_deg: float = SUN_RADIUS_DEG) -> np.ndarray:
    """[..., 3] radiance of a sun disc of `radius_deg` around the unit vector `sun`: full inside 80 % of
    the radius, fading smoothly to zero at 120 % (a hard rim this bright stays noisy at any spp)."""
    angle = np.degrees(np.arccos(np.clip(directions @ sun, -1.0, 1.0)))
    fade = np.clip((1.2 * radius_deg - angle) / (0.4 * radius_deg), 0.0, 1.0)
    return (fade * fade * (3 - 2 * fade))[..., None] * np.asarray(radiance, np.float64)


def aureole(directions: np.ndarray, sun: np.ndarray, peak, width_deg: float = 6.0) -> np.ndarray:
    """[..., 3] the glow of haze around the sun: `peak` next to it, falling off over `width_deg`."""
    angle = np.degrees(np.arccos(np.clip(directions @ sun, -1.0, 1.0)))
    return np.exp(-angle / width_deg)[..., None] * np.asarray(peak, np.float64)


def sky_gradient(directions: np.ndarray, zenith, horizon, ground) -> np.ndarray:
    """[..., 3] a clear sky: `horizon` colour at the horizon blending to `zenith` overhead, and a
    flat `ground` colour below the horizon (seen only past the end of the ground plane)."""
    height = directions[..., 2:3]
    blend = np.sqrt(np.clip(height, 0.0, 1.0))
    sky = (1 - blend) * np.asarray(horizon) + blend * np.asarray(zenith)
    return np.where(height >= 0, sky, np.asarray(ground))


def envmap(image: np.ndarray) -> dict:
    """A Mitsuba environment emitter from a lat-long [H, W, 3] radiance map, world z up."""
    return {"type": "envmap", "bitmap": image.astype(np.float32), "to_world": ENVMAP_TO_WORLD}


def _ground(near_seed: int, far_seed: int) -> dict:
    """A 24 m textured square under the objects and a 120 m one just beneath it reaching towards
    the horizon: one noise texture over 120 m would be blocks near the camera, and tiling it repeats."""
    return {
        "ground": panel(scale(12.0), diffuse(noise_texture(near_seed, low=0.08, high=0.5))),
        "far_ground": panel(
            place(translate(0, 0, -0.01), scale(60.0)), diffuse(noise_texture(far_seed, low=0.1, high=0.4))
        ),
    }


BACKLIT_SUN = direction(90.0, 7.0)
"""The sun of `backlit-sun`: low (7 degrees up), straight ahead of the forward arc (+y); the post
passes in front of it in a few views."""


def backlit_sun_content() -> dict:
    """Open sky with a small sun low ahead of the cameras, behind dark objects on a textured ground."""
    directions = sky_directions()
    sky = sky_gradient(directions, zenith=(0.25, 0.45, 1.0), horizon=(0.9, 0.85, 0.8), ground=(0.25, 0.22, 0.18))
    sky = (
        sky + aureole(directions, BACKLIT_SUN, (2.0, 1.8, 1.4)) + sun_disc(directions, BACKLIT_SUN, (4e4, 3.7e4, 3.2e4))
    )
    dark = diffuse(rgb(0.04, 0.035, 0.03))
    return {
        "sky": envmap(sky),
        **_ground(11, 12),
        "block": box((-0.8, 1.5, 0.6), (0.8, 0.6, 1.2), diffuse(noise_texture(13, low=0.02, high=0.12))),
        "post": box((0.3, 2.0, 1.0), (0.15, 0.15, 2.0), dark),
        "boulder": {"type": "sphere", "center": [1.0, 0.8, 0.35], "radius": 0.35, "bsdf": dark},
        "slab": box((0.0, 0.3, 0.08), (1.2, 0.5, 0.16), diffuse(noise_texture(14, low=0.03, high=0.15))),
    }


CLOUDY_SUN = direction(80.0, 14.0)
"""The sun of `sky-horizon`: higher up and off to the left of the arc, among the clouds."""


def clouds(directions: np.ndarray, seed: int) -> np.ndarray:
    """[...] cloud cover in [0, 1]: a sum of random waves (smooth, never repeating) on a flat cloud
    layer overhead, so clouds look large near the zenith and thin out towards the horizon."""
    rng = np.random.default_rng(seed)
    height = np.clip(directions[..., 2], 0.02, 1.0)
    plane = directions[..., :2] / height[..., None]  # where the ray meets the layer z = 1
    field = np.zeros(directions.shape[:-1])
    for octave in range(5):
        for _ in range(6):
            heading = rng.uniform(0, 2 * np.pi)
            wave = plane @ np.array([math.cos(heading), math.sin(heading)]) * 2.0 * 2**octave
            field += 0.6**octave * np.cos(wave + rng.uniform(0, 2 * np.pi))
    cover = np.clip((field / 3.0 + 0.1) / 0.6, 0.0, 1.0)
    return cover * cover * (3 - 2 * cover) * np.clip(directions[..., 2] / 0.05, 0.0, 1.0)


def hills(directions: np.ndarray, seed: int) -> np.ndarray:
    """[...] bool, whether a direction hits the distant hills: a ridge 1-4 degrees above the horizon."""
    rng = np.random.default_rng(seed)
    azimuth = np.arctan2(directions[..., 1], directions[..., 0])
    ridge = 2.5 + sum(
        amplitude * np.sin(frequency * azimuth + rng.uniform(0, 2 * np.pi))
        for frequency, amplitude in ((2, 0.8), (5, 0.5), (11, 0.3), (23, 0.15))
    )
    return np.degrees(np.arcsin(np.clip(directions[..., 2], -1.0, 1.0))) < ridge


def sky_horizon_content() -> dict:
    """A sky gradient with clouds and a sun among them, distant hills on the horizon, objects on a
    textured ground."""
    directions = sky_directions()
    sky = sky_gradient(directions, zenith=(0.2, 0.35, 0.9), horizon=(0.75, 0.8, 0.85), ground=(0.2, 0.22, 0.15))
    cover = clouds(directions, seed=21)[..., None]
    sky = (1 - cover) * sky + cover * np.array([1.1, 1.1, 1.15])
    sky = np.where(hills(directions, seed=22)[..., None], np.array([0.12, 0.16, 0.1]), sky)
    sky = sky + sun_disc(directions, CLOUDY_SUN, (1.0e5, 0.95e5, 0.85e5))
    return {
        "sky": envmap(sky),
        **_ground(23, 24),
        "crate": box((-0.6, 0.3, 0.3), (0.6, 0.6, 0.6), diffuse(noise_texture(25, tiles=0.5))),
        "ball": {"type": "sphere", "center": [0.4, -0.1, 0.35], "radius": 0.35, "bsdf": diffuse(noise_texture(26))},
        "pillar": box((0.9, 0.9, 0.6), (0.3, 0.3, 1.2), diffuse(noise_texture(27, tiles=0.5))),
    }


OUTDOOR_SCENES = (
    StudioScene(
        name="backlit-sun",
        description="open sky, a small sun low ahead behind dark objects, textured ground",
        content=backlit_sun_content,
        rig=CameraRig(
            target=(0.0, 0.8, 0.9), radius=4.0, azimuth_deg=(-110.0, -70.0), elevation_deg=(-2.0, 4.0), fov_deg=60
        ),
        spp=121,
        effects=("exposure", "noise", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="srgb"),
    ),
    StudioScene(
        name="sky-horizon",
        description="cloudy sky gradient with a sun, distant hills on the horizon, objects on a textured ground",
        content=sky_horizon_content,
        rig=CameraRig(
            target=(0.0, 0.5, 0.9), radius=4.0, azimuth_deg=(-115.0, -65.0), elevation_deg=(-1.0, 6.0), fov_deg=65
        ),
        spp=121,
        effects=("exposure", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="srgb"),
    ),
)
"""The outdoor scenes, appended to the studio's BUILTIN_SCENES."""
