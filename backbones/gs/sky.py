"""What lies at infinity behind the splats of an unbounded scene: an environment map.

The backbone appends one background row per pixel (the map's raw colour in that pixel's ray
direction) to its per-Gaussian colours, so the method's converters lift the sky and the sun to
HDR exactly as they lift a Gaussian; compositing adds that row with the weight the splats leave,
`image = splats + (1 - alpha) * background`.
"""

import math
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import WORLD_UP, Camera
from mono_hdr_plugin.core.environment import EnvironmentMap, up_from_cameras
from mono_hdr_plugin.data.io import write_exr


def uses_environment(background: str, scene: SceneInfo) -> bool:
    """--backbone.background: "environment", "none", or "auto" (an environment iff the scene is unbounded)."""
    return background == "environment" or (background == "auto" and scene.unbounded)


def make_environment(scene: SceneInfo) -> EnvironmentMap:
    """A map whose pole is the training cameras' up (world z without cameras), raw 0 everywhere:
    the LDR activation max(raw + 0.5, 0) starts the sky at mid grey, as far from black as from white."""
    cameras = scene.train_cameras
    up = up_from_cameras(torch.stack([c.c2w for c in cameras])) if cameras else WORLD_UP
    return EnvironmentMap(up, initial=0.0)


def background_rows(environment: EnvironmentMap, camera: Camera) -> Tensor:
    """The map's raw colour along each pixel's ray [H * W, C], pixels row-major (the rasteriser's
    pixel centres: integer + 0.5)."""
    _, directions = camera.rays()
    return environment(directions.reshape(-1, 3))


def environment_image(environment: EnvironmentMap) -> Tensor:
    """The map's raw values at the finest level's texel centres [width / 2, width, C], all levels
    summed: rows from straight up to straight down, columns azimuth -pi..pi in the map's frame
    (x: column width / 2, z: up; `environment.frame` rows in world coordinates)."""
    width = environment.textures[0].shape[-1]
    height = width // 2
    azimuth = ((torch.arange(width) + 0.5) / width * 2 - 1) * math.pi
    elevation = -((torch.arange(height) + 0.5) / height * 2 - 1) * (math.pi / 2)
    el, az = torch.meshgrid(elevation, azimuth, indexing="ij")
    local = torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], dim=-1)
    return environment(local @ environment.frame)


@torch.no_grad()
def export_environment(environment: EnvironmentMap, path: Path) -> Path:
    """Write the map as a lat-long float EXR of raw values (the PLY's f_dc convention: LDR colour
    max(raw + 0.5, 0), HDR through the exported converters)."""
    write_exr(path, environment_image(environment).float().numpy().astype(np.float32))
    return path


def seen_by_cameras(points: Tensor, cameras: list[Camera], margin: float = 0.0) -> Tensor:
    """[N] bool: which points some camera sees in front of its near plane, inside its image widened
    by `margin` times its size on every side."""
    seen = torch.zeros(points.shape[0], dtype=torch.bool)
    for camera in cameras:
        pixels, depth = camera.project(points)
        pad_x, pad_y = margin * camera.width, margin * camera.height
        inside = (pixels[:, 0] >= -pad_x) & (pixels[:, 0] < camera.width + pad_x)
        inside &= (pixels[:, 1] >= -pad_y) & (pixels[:, 1] < camera.height + pad_y)
        seen |= inside & (depth > camera.near)
    return seen


def random_points_in_view(count: int, low: Tensor, high: Tensor, cameras: list[Camera]) -> Tensor:
    """`count` points uniform in the box [low, high] that some training camera sees (in its image,
    beyond its near plane): in an unbounded scene the box reaches behind the cameras, and points
    no view sees never get a gradient to move them. Falls back to the box when no camera sees it."""
    kept: list[Tensor] = []
    drawn = 0
    while sum(k.shape[0] for k in kept) < count and drawn < 64 * count:
        candidates = low + torch.rand(4 * count, 3) * (high - low)
        drawn += candidates.shape[0]
        kept.append(candidates[seen_by_cameras(candidates, cameras)])
    points = torch.cat(kept)[:count] if kept else torch.empty(0, 3)
    if points.shape[0] < count:  # nothing (or too little) in view: the plain box
        points = torch.cat([points, low + torch.rand(count - points.shape[0], 3) * (high - low)])
    return points
