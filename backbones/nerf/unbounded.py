"""Unbounded scenes: nerfacto's scene contraction and samples that reach far, linear in disparity.

Points are first normalised (the scene box's longest side spans [-1, 1], the "unit region"); the
contraction keeps that region as it is and squeezes everything outside into the shell up to the
cube of half-size 2, so a field on [-2, 2]^3 covers all of space. Along a ray, samples are uniform
in distance inside the unit region and linear in disparity beyond it, up to a far distance.

The far part of a ray is parametrised by a warped distance u (world units): u runs linearly from
the ray's exit of the unit region over `far_length` while the distance t runs linearly in
disparity to the far distance, so occupancy marching and resampling work on u as they do on t
inside the box.
"""

import torch
from torch import Tensor

# The contracted cube is open: field coordinates on its surface stand for points this far inside
# it (1 / (2 - 1.999) = 1000 unit-region half sides away), so inverting the contraction stays finite.
_OPEN_CUBE = 1.999


def contract(points: Tensor) -> Tensor:
    """nerfacto's L-inf contraction of normalised points [..., 3]: identity where ||x||_inf <= 1,
    else (2 - 1 / ||x||_inf) x / ||x||_inf, inside the open cube of half-size 2."""
    norm = points.abs().amax(dim=-1, keepdim=True)
    outer = norm.clamp_min(1.0)
    return torch.where(norm <= 1.0, points, (2.0 - 1.0 / outer) * points / outer)


def uncontract(points: Tensor) -> Tensor:
    """The inverse of contract on [..., 3] (||y||_inf < 2; the cube's surface is read as _OPEN_CUBE)."""
    norm = points.abs().amax(dim=-1, keepdim=True)
    outer = norm.clamp(1.0, _OPEN_CUBE)
    scale = 1.0 / (2.0 - outer)  # ||x||_inf, from ||y||_inf = 2 - 1 / ||x||_inf
    return torch.where(norm <= 1.0, points, points / norm.clamp_min(1.0) * scale)


def disparity_distances(t_start: Tensor, t_end: float, fractions: Tensor) -> Tensor:
    """Distances linear in disparity: fraction 0 -> t_start [N] (> 0), 1 -> t_end. fractions [N, K] -> [N, K]."""
    return 1.0 / ((1.0 - fractions) / t_start[:, None] + fractions / t_end)


def unwarp(u: Tensor, t_start: Tensor, far_length: float, far: float) -> Tensor:
    """Warped distances u [N, S] -> distances t [N, S]: t = u up to the ray's t_start [N], then
    linear in disparity from t_start to `far` over the next `far_length` of u."""
    beyond = ((u - t_start[:, None]) / far_length).clamp(0.0, 1.0)
    return torch.where(u <= t_start[:, None], u, disparity_distances(t_start, far, beyond))


def far_candidates(
    t_start: Tensor, far_length: float, count: int, jitter: Tensor | None
) -> tuple[Tensor, Tensor, Tensor]:
    """`count` bins evenly spaced in u over [t_start, t_start + far_length] per ray, one sample in each.

    t_start: [N]; jitter: [N, count] in [0, 1) or None (bin centres).
    Returns u [N, count], the bin length (in u) [N, count] and the samples' fraction in their bins.
    """
    fraction = jitter if jitter is not None else torch.full((t_start.shape[0], count), 0.5, device=t_start.device)
    step = far_length / count
    bins = torch.arange(count, dtype=t_start.dtype, device=t_start.device)
    return t_start[:, None] + (bins + fraction) * step, torch.full_like(fraction, step), fraction


def contracted_lengths(origins: Tensor, directions: Tensor, t0: Tensor, t1: Tensor) -> Tensor:
    """Length, in contracted normalised space, of the chord from t0 to t1 [N, S] along each ray.

    origins, directions: [N, 3] in normalised units (a world distance t reaches origin + t * direction).
    """
    start = contract(origins[:, None] + t0[..., None] * directions[:, None])
    end = contract(origins[:, None] + t1[..., None] * directions[:, None])
    return (end - start).norm(dim=-1)


def camera_region(cameras: list, fallback_center: Tensor) -> tuple[Tensor, float] | None:
    """The unit region of a contracted scene: the cube around the point the cameras look at
    (least squares over their optical axes, pulled weakly to fallback_center where the axes are
    parallel), just large enough to hold the cameras. None without cameras.

    An unbounded scene's box holds the far ground and the horizon; the cameras' region keeps the
    grid's full resolution for what they are looking at and leaves the rest to the contraction.
    """
    if not cameras:
        return None
    centers = torch.stack([camera.center.double() for camera in cameras])
    axes = torch.stack([camera.c2w[:3, 2].double() for camera in cameras])
    axes = axes / axes.norm(dim=-1, keepdim=True)
    projectors = torch.eye(3, dtype=torch.float64) - axes[:, :, None] * axes[:, None, :]
    weak = 1e-3 * len(cameras)
    matrix = projectors.sum(0) + weak * torch.eye(3, dtype=torch.float64)
    target = (projectors @ centers[:, :, None]).sum(0)[:, 0] + weak * fallback_center.double()
    center = torch.linalg.solve(matrix, target)
    half_size = float((centers - center).abs().amax()) * 1.05
    return center.float(), max(half_size, 1e-3)
