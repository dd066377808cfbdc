"""What lies at infinity as splats: a fixed shell of "sky Gaussians" around an unbounded scene.

The alternative to the environment map (sky.py), chosen with `--backbone.background sky-gaussians`:
Gaussians on a sphere far beyond the scene, spread evenly (a Fibonacci sphere) over the directions
some training camera sees, rasterised together with the scene's Gaussians. They are behind every
scene Gaussian in depth, so the splats composite over them as over any background, and their raw
colours are rows like any Gaussian's, so every method's converters lift them to HDR.

Only their colours learn (raw values, LDR max(raw + 0.5, 0): SH degree 0 without the C0 factor,
mid grey at raw 0 like the environment map). Positions, isotropic scales and opacity (1) are fixed:
a sky Gaussian that became transparent would open a hole onto black, there being nothing behind
it. They live in their own module, outside GAUSSIAN_PARAMETERS, so no densification strategy
(relocate, grow, clone, split, prune, opacity reset) ever sees them.
"""

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import torch
from torch import Tensor, nn

from backbones.gs.ply import export_ply
from backbones.gs.rasterizer import ProjectedGaussians
from backbones.gs.sh import SH_C0
from backbones.gs.sky import seen_by_cameras
from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import Camera

RADIUS_FACTOR = 10.0
"""The shell's radius: this times the farthest scene-box corner or camera from its centre."""
MARGIN = 0.1
"""Directions a camera sees within this fraction of its image size beyond the frame count as seen."""


def fibonacci_directions(count: int) -> Tensor:
    """`count` unit vectors spread evenly over the sphere [count, 3] (golden-angle spiral)."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / count
    radius = (1 - z * z).clamp_min(0).sqrt()
    theta = math.pi * (3 - math.sqrt(5)) * i
    return torch.stack([radius * theta.cos(), radius * theta.sin(), z], -1).float()


def shell_centre(scene: SceneInfo) -> Tensor:
    """The point the training cameras look at (least squares over their optical axes, pulled weakly
    towards the scene box's centre where the axes are parallel); the box's centre without cameras."""
    fallback = scene.center.double()
    if not scene.train_cameras:
        return fallback.float()
    system = 1e-3 * len(scene.train_cameras) * torch.eye(3, dtype=torch.float64)
    rhs = system @ fallback
    for camera in scene.train_cameras:
        axis = camera.c2w[:3, 2].double()
        projector = torch.eye(3, dtype=torch.float64) - torch.outer(axis, axis)
        system = system + projector
        rhs = rhs + projector @ camera.center.double()
    return torch.linalg.solve(system, rhs).float()


def shell_radius(scene: SceneInfo, centre: Tensor) -> float:
    """RADIUS_FACTOR times the farthest box corner or camera centre from `centre`: behind anything
    the scene's Gaussians start on, and far enough that a camera moving across the rig sees the
    shell shift by a small fraction of a degree (it stands for infinity)."""
    low, high = scene.bounds_min.float(), scene.bounds_max.float()
    corners = torch.stack([torch.where(torch.tensor(bits, dtype=torch.bool), high, low) for bits in _CORNER_BITS])
    points = [corners] + ([torch.stack([c.center.float() for c in scene.train_cameras])] if scene.train_cameras else [])
    return RADIUS_FACTOR * max(float((torch.cat(points) - centre).norm(dim=-1).max()), 1e-3)


_CORNER_BITS = [(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1)]


def shell_directions(count: int, centre: Tensor, radius: float, cameras: list[Camera]) -> tuple[Tensor, int]:
    """About `count` directions of a Fibonacci sphere that some camera sees (with MARGIN), and the
    size of the whole sphere they were kept from (its density sets the scale). Without cameras,
    or when no camera sees the shell, the whole sphere of `count`."""
    if not cameras:
        return fibonacci_directions(count), count
    total, kept = count, fibonacci_directions(count)
    for _ in range(4):  # the visible fraction of a denser sphere is the same: converges in 2-3 rounds
        directions = fibonacci_directions(total)
        kept = directions[seen_by_cameras(centre + radius * directions, cameras, MARGIN)]
        if kept.shape[0] == 0:
            return fibonacci_directions(count), count
        if abs(kept.shape[0] - count) <= 0.02 * count:
            break
        total = max(count, round(total * count / kept.shape[0]))
    return kept, total


class SkyGaussians(nn.Module):
    """The shell: fixed means [S, 3] and isotropic scales [S] (buffers), learned raw colours [S, 3]."""

    means: Tensor
    scales: Tensor

    def __init__(self, scene: SceneInfo, count: int, scale: float):
        super().__init__()
        centre = shell_centre(scene)
        radius = shell_radius(scene, centre)
        directions, sphere_size = shell_directions(count, centre, radius, scene.train_cameras)
        spacing = radius * math.sqrt(4 * math.pi / sphere_size)  # sqrt of the area per point
        self.register_buffer("means", centre + radius * directions)
        self.register_buffer("scales", torch.full((directions.shape[0],), scale * spacing))
        self.colors = nn.Parameter(torch.zeros(directions.shape[0], 3))

    @property
    def count(self) -> int:
        return self.means.shape[0]

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the shell's size depends on the scene's cameras: take the checkpoint's shapes
        for name in ("means", "scales"):
            if prefix + name in state_dict:
                self.register_buffer(name, torch.empty_like(state_dict[prefix + name]))
        if prefix + "colors" in state_dict:
            self.colors = nn.Parameter(torch.empty_like(state_dict[prefix + "colors"]))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def with_sky(sky: SkyGaussians, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor) -> tuple:
    """The scene's Gaussians [N] followed by the sky's [S]: means, quats, scales [N + S, 3] and
    opacities (the sky's 1) for one projection."""
    count = sky.count
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(count, 4)
    return (
        torch.cat([means, sky.means]),
        torch.cat([quats, identity]),
        torch.cat([scales, sky.scales[:, None].expand(count, 3)]),
        torch.cat([opacities, torch.ones(count)]),
    )


def scene_rows(projected: ProjectedGaussians, scene_count: int) -> int:
    """How many of the visible rows are scene Gaussians (the sky's indices follow the scene's, and
    projected.index is ascending)."""
    return int(torch.searchsorted(projected.index, torch.tensor(scene_count)))


def scene_projection(projected: ProjectedGaussians, scene_count: int) -> ProjectedGaussians:
    """The projection restricted to the scene's Gaussians, for density control: index, radii and the
    per-row tensors cut to them, means2d a leaf holding the rows of means2d.grad (the strategies'
    screen-space gradient). The tile lists still describe the full projection: not for rasterising."""
    visible = scene_rows(projected, scene_count)
    means2d = projected.means2d.detach()[:visible].clone()
    if projected.means2d.grad is not None:
        means2d.grad = projected.means2d.grad[:visible]
    return dataclasses.replace(
        projected,
        index=projected.index[:visible],
        radii=projected.radii[:scene_count],
        means2d=means2d,
        conics=projected.conics[:visible],
        depths=projected.depths[:visible],
        opacities=projected.opacities[:visible],
        boxes=projected.boxes[:visible],
    )


@torch.no_grad()
def export_sky(sky: SkyGaussians, path) -> Path:
    """Write the shell as its own 3DGS PLY (degree-0 f_dc = raw / C0, opacity logit of 0.9999): kept
    out of the scene's PLY, whose bounds a sphere ten times the scene's size would swamp in a viewer."""
    count = sky.count
    shell = SimpleNamespace(
        means=sky.means,
        sh_dc=(sky.colors / SH_C0)[:, None, :],
        sh_rest=torch.zeros(count, 0, 3),
        opacity_logits=torch.full((count,), math.log(0.9999 / 0.0001)),
        log_scales=sky.scales.log()[:, None].expand(count, 3),
        quats=torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(count, 4),
    )
    return export_ply(shell, path)
