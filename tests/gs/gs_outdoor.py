"""A tiny analytic outdoor capture: open sky, a sun ~2 px wide low in the frame, a dark backlit
sphere, a checkered ground; no points (as the HDR-NeRF synthetic layout), photographed along a
forward arc. Dynamic range sun : dark sphere ~1e5; the sun is clipped in every photo."""

import math

import torch

from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.data.captures import bounds_from_cameras
from mono_hdr_plugin.data.dataset import SceneData, View

SUN = torch.nn.functional.normalize(torch.tensor([0.0, 1.0, 0.12]), dim=0)
SUN_RADIANS = math.radians(1.2)
SUN_RADIANCE = 3000.0
SPHERE_CENTRE, SPHERE_RADIUS, SPHERE_RADIANCE = torch.tensor([0.0, 4.0, 0.6]), 0.6, 0.03
EXPOSURE = 0.25


def radiance(origins: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """HDR radiance [N, 3] along rays [N, 3] (z up, ground z = 0)."""
    up = directions[:, 2]
    horizon, zenith = torch.tensor([1.2, 1.3, 1.5]), torch.tensor([0.3, 0.5, 1.2])
    blend = up.clamp(0, 1).sqrt()[:, None]
    colour = horizon * (1 - blend) + zenith * blend
    sun = (directions @ SUN) > math.cos(SUN_RADIANS)
    colour = torch.where(sun[:, None], torch.full_like(colour, SUN_RADIANCE), colour)
    ground_t = -origins[:, 2] / up.clamp(max=-1e-6)
    hits_ground = up < -1e-6
    hit = origins + ground_t[:, None] * directions
    checker = ((hit[:, 0].floor() + hit[:, 1].floor()) % 2)[:, None]
    ground = checker * torch.tensor([0.45, 0.35, 0.25]) + (1 - checker) * torch.tensor([0.22, 0.3, 0.18])
    colour = torch.where(hits_ground[:, None], ground, colour)
    offset = origins - SPHERE_CENTRE
    b = (offset * directions).sum(-1)
    disc = b * b - (offset * offset).sum(-1) + SPHERE_RADIUS**2
    sphere = (disc > 0) & (-b - disc.clamp_min(0).sqrt() > 0)
    return torch.where(sphere[:, None], torch.full_like(colour, SPHERE_RADIANCE), colour)


def render_hdr(camera: Camera, supersample: int = 3) -> torch.Tensor:
    """[H, W, 3] mean radiance over supersample^2 rays per pixel."""
    total = torch.zeros(camera.height * camera.width, 3)
    for i in range(supersample):
        for j in range(supersample):
            ys, xs = torch.meshgrid(
                torch.arange(camera.height) + (i + 0.5) / supersample,
                torch.arange(camera.width) + (j + 0.5) / supersample,
                indexing="ij",
            )
            pixels = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)
            origins, directions = camera.with_pixels(pixels).rays()
            total += radiance(origins, directions)
    return (total / supersample**2).reshape(camera.height, camera.width, 3)


def outdoor_capture(size: int = 48, views: int = 12, unbounded: bool = True) -> SceneData:
    """Every third view is a test view. `unbounded` is the metadata the data side would set."""
    focal = 0.5 * size / math.tan(math.radians(30))
    all_views = []
    for index in range(views):
        angle = math.radians(-20 + 40 * index / (views - 1))
        eye = torch.tensor([3.0 * math.sin(angle), -3.0 * math.cos(angle) + 0.5, 1.0])
        c2w = look_at(eye, torch.tensor([0.0, 4.0, 1.1]))
        camera = Camera(c2w, fx=focal, fy=focal, cx=size / 2, cy=size / 2, width=size, height=size, far=1e3)
        hdr = render_hdr(camera)
        ldr = (hdr * EXPOSURE).clamp(0, 1) ** (1 / 2.2)
        all_views.append(View(camera, ldr, EXPOSURE, index, name=f"r_{index}", hdr=hdr))
    train = [v for v in all_views if v.view_id % 3 != 1]
    test = [v for v in all_views if v.view_id % 3 == 1]
    low, high = bounds_from_cameras([v.camera for v in train])
    return SceneData("outdoor-tiny", train, test, low, high, metadata={"unbounded": unbounded})


def sun_pixels(camera: Camera) -> torch.Tensor:
    """[H, W] bool: pixels whose centre ray lies within the sun's disc plus one pixel."""
    _, directions = camera.rays()
    pixel_radians = 1.0 / camera.fx
    return (directions @ SUN) > math.cos(SUN_RADIANS + pixel_radians)
