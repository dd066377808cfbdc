"""What a studio scene is: Mitsuba 3 content, a camera rig, render settings, capture effects.

Scene content is a plain Python dict in Mitsuba's `load_dict` format whose transforms are
numpy [4, 4] matrices (converted when rendering), so a definition can be hashed for the
render cache without importing Mitsuba.
"""

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch

from mono_hdr_plugin.apps.studio.capture import CaptureSettings, validate_effects
from mono_hdr_plugin.core.cameras import Camera, focal_from_fov, look_at

STUDIO_EXPOSURES = (0.125, 0.5, 2.0, 8.0, 32.0)
"""t1..t5 in seconds, the synthetic HDR-NeRF/HDR-GS exposure times."""


INFINITE_EMITTERS = ("envmap", "constant")
"""Mitsuba emitters that surround the scene at infinity."""


@dataclass(frozen=True)
class CameraRig:
    """Cameras on a sphere around `target`: an arc (forward-facing) or a full hemisphere sweep.

    View i sits at azimuth lerp(azimuth_deg, i / (views - 1)) and an elevation that swings
    between the two `elevation_deg` values, all looking at `target` with world z up.
    """

    target: tuple[float, float, float]
    radius: float
    azimuth_deg: tuple[float, float] = (-120.0, -60.0)
    elevation_deg: tuple[float, float] = (15.0, 30.0)
    fov_deg: float = 50.0
    views: int = 35

    def eyes(self) -> np.ndarray:
        """[views, 3] camera centres."""
        steps = np.linspace(0.0, 1.0, self.views)
        azimuth = np.radians(np.interp(steps, [0, 1], self.azimuth_deg))
        # Elevation swings up and down three times so the views do not all lie on one circle.
        swing = 0.5 - 0.5 * np.cos(steps * 6 * np.pi)
        elevation = np.radians(np.interp(swing, [0, 1], self.elevation_deg))
        offsets = np.stack(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], -1
        )
        return np.asarray(self.target) + self.radius * offsets

    def cameras(self, width: int, height: int) -> list[Camera]:
        """One OpenCV camera per view; principal point at the image centre, square pixels."""
        focal = focal_from_fov(math.radians(self.fov_deg), width)
        target = torch.tensor(self.target, dtype=torch.float32)
        return [
            Camera(
                c2w=look_at(torch.tensor(eye, dtype=torch.float32), target),
                fx=focal,
                fy=focal,
                cx=width / 2,
                cy=height / 2,
                width=width,
                height=height,
            )
            for eye in self.eyes()
        ]


@dataclass(frozen=True)
class StudioScene:
    """A built-in synthetic HDR scene.

    content: builds the Mitsuba scene dict (shapes, emitters, no sensor or integrator).
    effects: the capture effects the simulator applies to this scene, and only those.
    """

    name: str
    description: str
    content: Callable[[], dict]
    rig: CameraRig
    resolution: tuple[int, int] = (128, 128)
    spp: int = 289
    """Samples per pixel of each of the two renders whose mean is the ground truth: the square of a
    prime (what the orthogonal-array sampler takes)."""
    max_depth: int = 2
    """Path length: 2 is direct light only, which converges in hundreds of samples (interreflections
    and caustics of small bright lights need orders of magnitude more)."""
    effects: tuple[str, ...] = ("exposure", "crf", "clip", "quantize")
    capture: CaptureSettings = field(default_factory=CaptureSettings)
    exposures: tuple[float, ...] = STUDIO_EXPOSURES
    key_value: float = 0.1
    """Median scene radiance is scaled so that the middle exposure maps it to this value."""

    def __post_init__(self):
        validate_effects(self.effects)
        root = math.isqrt(self.spp)
        if root * root != self.spp or root < 2 or any(root % d == 0 for d in range(2, math.isqrt(root) + 1)):
            raise ValueError(
                f"scene {self.name!r}: spp must be the square of a prime (4, 9, 25, 49, 121, 169, "
                f"289, 361, ...) for orthogonal-array sampling, got {self.spp}"
            )

    @property
    def width(self) -> int:
        return self.resolution[0]

    @property
    def height(self) -> int:
        return self.resolution[1]

    def cameras(self) -> list[Camera]:
        return self.rig.cameras(self.width, self.height)

    def unbounded(self) -> bool:
        """Whether the scene has light at infinity (an environment emitter: an open sky), which a
        ray that misses every surface sees."""
        return any(isinstance(item, dict) and item.get("type") in INFINITE_EMITTERS for item in self.content().values())

    def split(self, view: int) -> Literal["train", "test"]:
        """Alternate views: even views train, odd views test."""
        return "train" if view % 2 == 0 else "test"


def translate(x: float, y: float, z: float) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = (x, y, z)
    return matrix


def scale(x: float, y: float | None = None, z: float | None = None) -> np.ndarray:
    return np.diag([x, x if y is None else y, x if z is None else z, 1.0])


def rotate(axis: str, degrees: float) -> np.ndarray:
    """Rotation about a world axis ('x', 'y' or 'z')."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    matrix = np.eye(4)
    matrix[i, i], matrix[i, j], matrix[j, i], matrix[j, j] = c, -s, s, c
    return matrix


def place(*transforms: np.ndarray) -> np.ndarray:
    """Compose transforms applied right to left (the last one first), like Mitsuba's chains."""
    matrix = np.eye(4)
    for transform in transforms:
        matrix = matrix @ transform
    return matrix


def rgb(r: float, g: float | None = None, b: float | None = None) -> dict:
    return {"type": "rgb", "value": [r, r if g is None else g, r if b is None else b]}


def diffuse(colour: dict) -> dict:
    return {"type": "diffuse", "reflectance": colour}


def checker(colour0: dict, colour1: dict, tiles: float) -> dict:
    return {"type": "checkerboard", "color0": colour0, "color1": colour1, "to_uv": scale(tiles, tiles, 1.0)}


def noise_image(seed: int, size: int = 512) -> np.ndarray:
    """[size, size, 3] in [0, 1]: random colours in square cells of 4, 16 and 64 per side, summed.
    Blobs at every scale give SIFT features at every distance, and no two look alike."""
    rng = np.random.default_rng(seed)
    image = np.zeros((size, size, 3))
    for cells, weight in ((4, 1.0), (16, 0.8), (64, 0.6)):
        grid = rng.random((cells, cells, 3))
        image += weight * np.kron(grid, np.ones((size // cells, size // cells, 1)))
    return (image - image.min()) / (image.max() - image.min())


def noise_texture(seed: int, tiles: float = 1.0, low: float = 0.05, high: float = 0.85) -> dict:
    """A diffuse reflectance texture of noise_image(seed) at 256 px, scaled into [low, high],
    repeated `tiles` times across a shape. Structure from motion matches its features between
    photos; a checkerboard's corners all look alike and mislead it."""
    image = low + (high - low) * noise_image(seed, size=256)
    return {
        "type": "bitmap",
        "filter_type": "bilinear",
        "bitmap": image.astype(np.float32),
        "to_uv": scale(tiles, tiles, 1.0),
    }


def box(centre, size, bsdf: dict) -> dict:
    """An axis-aligned box with the given centre and full size (x, y, z)."""
    return {"type": "cube", "to_world": place(translate(*centre), scale(*(s / 2 for s in size))), "bsdf": bsdf}


def panel(transform: np.ndarray, bsdf: dict) -> dict:
    """A rectangle ([-1, 1]^2 in its own xy plane, normal +z) placed by `transform`."""
    return {"type": "rectangle", "to_world": transform, "bsdf": bsdf}


def lamp(centre, radius: float, radiance: tuple[float, float, float]) -> dict:
    """A visible spherical emitter (a bulb)."""
    return {
        "type": "sphere",
        "center": list(centre),
        "radius": radius,
        "emitter": {"type": "area", "radiance": rgb(*radiance)},
    }


def projector(
    origin,
    target,
    up,
    fov_deg: float,
    irradiance: tuple[float, float, float],
    aspect: float = 1.0,
    soft_edge: float = 0.0,
) -> dict:
    """A point light that throws a rectangle of uniform light (a sun patch through a window):
    Mitsuba's projector with a constant image of width / height `aspect`. `soft_edge` (a
    fraction of the width) fades the border smoothly, as the sun's disc does; a hard edge
    between a light this bright and the dark floor stays noisy at any sample count."""
    width = 64
    height = max(2, round(width / aspect))
    image = np.ones((height, width), np.float32)
    if soft_edge > 0:

        def ramp(n: int) -> np.ndarray:
            return np.clip(np.minimum(np.arange(n) + 0.5, n - np.arange(n) - 0.5) / (soft_edge * width), 0, 1)

        image = np.outer(ramp(height), ramp(width))
        image = image * image * (3 - 2 * image)  # smoothstep: no kink where the fade starts
    return {
        "type": "projector",
        "fov": fov_deg,
        "scale": 1.0,
        "irradiance": {
            "type": "bitmap",
            "filter_type": "bilinear",
            "bitmap": image[..., None] * np.asarray(irradiance, np.float32),
        },
        "to_world": look_at_matrix(origin, target, up),
    }


def look_at_matrix(origin, target, up) -> np.ndarray:
    """Mitsuba's look-at transform (+z towards the target, +y towards `up`) as a numpy [4, 4]."""
    origin, target, up = (np.asarray(v, np.float64) for v in (origin, target, up))
    forward = (target - origin) / np.linalg.norm(target - origin)
    left = np.cross(up, forward)
    left /= np.linalg.norm(left)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = left, np.cross(forward, left), forward, origin
    return matrix
