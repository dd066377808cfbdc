"""Volume rendering: compositing weights from densities, and the compositing closure.

Density is constant from one sample to the next (the last sample reaches t_far), so a ray's
weights are  w_i = T_i (1 - exp(-sigma_i delta_i)),  T_i = exp(-sum_{j<i} sigma_j delta_j),
and they sum to 1 - exp(-sum sigma delta) <= 1 exactly: no epsilon, no NaN on empty rays.
"""

from collections.abc import Callable

import torch
from torch import Tensor


def sample_deltas(t: Tensor, t_far: Tensor) -> Tensor:
    """Length each sample stands for: distance to the next sample, the last one to t_far.

    t: [N, S] sorted sample distances; t_far: [N]. Returns [N, S] >= 0.
    """
    ends = torch.cat([t[:, 1:], t_far[:, None]], dim=-1)
    return (ends - t).clamp(min=0.0)


def compositing_weights(densities: Tensor, deltas: Tensor) -> Tensor:
    """Volume-rendering weights of the samples of each ray.

    densities: [N, S] >= 0 (finite); deltas: [N, S] >= 0, in the units densities are per.
    Returns weights [N, S] >= 0 with weights.sum(-1) <= 1.
    """
    optical_depth = densities * deltas
    # Exclusive prefix sum written out, not cumsum - depth: that loses small terms once a huge
    # (opaque) depth has been added.
    depth_before = torch.cat(
        [torch.zeros_like(optical_depth[:, :1]), torch.cumsum(optical_depth[:, :-1], dim=-1)], dim=-1
    )
    alpha = -torch.expm1(-optical_depth)
    return alpha * torch.exp(-depth_before)


def add_background(image: Tensor, accumulation: Tensor, background: Tensor) -> Tensor:
    """image [N, C] + (1 - accumulation [N]) * background [3] on each group of 3 channels; a black
    background adds nothing and allows any C."""
    if not bool(background.abs().sum() > 0):
        return image
    channels = image.shape[-1]
    if channels % 3:
        raise ValueError(
            f"composite: a non-black background needs channels in groups of 3, "
            f"got {channels}; set the NeRF background to (0, 0, 0)"
        )
    return image + (1.0 - accumulation[:, None]) * background.to(image).repeat(channels // 3)


def make_composite(weights: Tensor, output_shape: tuple[int, ...], background: Tensor) -> Callable[[Tensor], Tensor]:
    """The closure LdrFeatures.composite: per-sample values to an image with these weights.

    weights: [N, S] with N = prod(output_shape); background: [3], added as
    (1 - accumulation) * background to each group of 3 channels.
    The closure maps values [N, S, C] -> [*output_shape, C].
    """
    accumulation = weights.sum(dim=-1)

    def composite(values: Tensor) -> Tensor:
        if values.shape[:-1] != weights.shape:
            raise ValueError(
                f"composite: values must have shape [{weights.shape[0]}, "
                f"{weights.shape[1]}, C] (rays, samples, channels), got {tuple(values.shape)}"
            )
        image = add_background(torch.einsum("ns,nsc->nc", weights, values), accumulation, background)
        return image.reshape(*output_shape, values.shape[-1])

    return composite


def make_packed_composite(
    weights: Tensor, ray_indices: Tensor, accumulation: Tensor, output_shape: tuple[int, ...], background: Tensor
) -> Callable[[Tensor], Tensor]:
    """The closure LdrFeatures.composite for packed samples (only those that contribute).

    weights: [M] of the kept samples; ray_indices: [M] the ray each belongs to (long);
    accumulation: [N] each ray's total weight, N = prod(output_shape), dropped samples included;
    background: [3], added as (1 - accumulation) * background to each group of 3 channels.
    The closure maps values [M, C] -> [*output_shape, C].
    """
    num_rays = accumulation.shape[0]

    def composite(values: Tensor) -> Tensor:
        if values.dim() != 2 or values.shape[0] != weights.shape[0]:
            raise ValueError(
                f"composite: values must have shape [{weights.shape[0]}, C] (packed samples, "
                f"channels), got {tuple(values.shape)}"
            )
        image = values.new_zeros(num_rays, values.shape[-1]).index_add(0, ray_indices, weights[:, None] * values)
        return add_background(image, accumulation, background).reshape(*output_shape, values.shape[-1])

    return composite
