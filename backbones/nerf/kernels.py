"""The C++ kernels of the grid field behind plain torch signatures (with autograd).

Their plain-torch twins, slow and obvious, are in backbones/nerf/reference.py; tests compare
the two on the same inputs, values and gradients.
"""

import torch
from torch import Tensor

from backbones.nerf._extension import load_extension
from backbones.nerf.reference import grid_encode_reference


class _GridEncode(torch.autograd.Function):
    @staticmethod
    def forward(ctx, positions: Tensor, table: Tensor, resolutions: Tensor, offsets: Tensor) -> Tensor:
        positions = positions.contiguous()
        ctx.save_for_backward(positions, table, resolutions, offsets)
        ctx.table_rows = table.shape[0]
        return load_extension().grid_encode_forward(positions, table.contiguous(), resolutions, offsets)

    @staticmethod
    def backward(ctx, grad_features: Tensor):
        positions, table, resolutions, offsets = ctx.saved_tensors
        grad_positions = grad_table = None
        if ctx.needs_input_grad[1]:
            grad_table = load_extension().grid_encode_backward(
                grad_features.contiguous(), positions, resolutions, offsets, ctx.table_rows
            )
        if ctx.needs_input_grad[0]:  # camera pose refinement: the samples move with the ray
            grad_positions = _grid_encode_position_gradient(positions, table, resolutions, offsets, grad_features)
        return grad_positions, grad_table, None, None


def _grid_encode_position_gradient(
    positions: Tensor, table: Tensor, resolutions: Tensor, offsets: Tensor, grad_features: Tensor
) -> Tensor:
    """The gradient of the grid features with respect to the positions, through the torch twin
    (grid_sample differentiates its sampling positions): only runs whose positions require grad, which
    only a refined camera pose makes them, pay for it; the kernel differentiates the table alone."""
    with torch.enable_grad():
        moving = positions.detach().requires_grad_()
        features = grid_encode_reference(moving, table.detach(), resolutions, offsets)
        (gradient,) = torch.autograd.grad(features, moving, grad_features.to(features.dtype))
    return gradient.to(positions.dtype)


def grid_encode(positions: Tensor, table: Tensor, resolutions: Tensor, offsets: Tensor) -> Tensor:
    """Multi-resolution trilinear grid features.

    positions: [M, 3] in [-1, 1] (outside: clamped to the border); table: [V, F], the levels one
    after another, vertex (x, y, z) of level l at row offsets[l] + (z R + y) R + x with
    R = resolutions[l] and position -1 + 2 (x, y, z) / (R - 1); resolutions, offsets: [L] int64.
    Returns [M, L * F], level-major. Differentiable with respect to `table` (the kernel) and to
    `positions` (the torch twin, only when they require grad: camera pose refinement).
    """
    return _GridEncode.apply(positions, table, resolutions, offsets)


@torch.no_grad()
def march_rays(
    origins: Tensor,
    directions: Tensor,
    t_near: Tensor,
    t_far: Tensor,
    occupancy: Tensor,
    center: Tensor,
    scale: float,
    min_step: float,
    max_samples: int,
    jitter: Tensor | None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Stratified samples over the occupied stretches of each ray's [t_near, t_far].

    origins, directions: [N, 3] world (unit directions); t_near, t_far: [N] world distances;
    occupancy: [G, G, G] bool or uint8 over the cube [-1, 1]^3 of normalised positions
    (position - center) / scale, indexed [z, y, x]; min_step: the closest sample spacing, in
    world units; jitter: [N, max_samples] in [0, 1) (training) or None (bin centres).
    A ray whose occupied length is L gets n = min(max_samples, ceil(L / min_step)) samples;
    sample k stands for the k-th 1/n of the occupied length (its `delta`).
    Returns t [N, S], delta [N, S] (world units; 0 past a ray's count) and counts [N] int64.
    """
    empty = torch.empty(0, dtype=torch.float32)
    return tuple(
        load_extension().march_rays(
            origins.float().contiguous(),
            directions.float().contiguous(),
            t_near.float().contiguous(),
            t_far.float().contiguous(),
            occupancy.to(torch.uint8).contiguous(),
            center.float().contiguous(),
            float(scale),
            float(min_step),
            int(max_samples),
            empty if jitter is None else jitter.float().contiguous(),
        )
    )
