"""Plain-torch twins of the grid-field kernels (backbones/nerf/kernels.py): slow and obvious.

They define what the kernels compute; tests run both on the same inputs and compare values
and gradients. Not used for training.
"""

import torch
import torch.nn.functional as F
from torch import Tensor


def grid_encode_reference(positions: Tensor, table: Tensor, resolutions: Tensor, offsets: Tensor) -> Tensor:
    """kernels.grid_encode with torch's grid_sample, one level at a time."""
    features = []
    for resolution, offset in zip(resolutions.tolist(), offsets.tolist()):
        level = table[offset : offset + resolution**3].reshape(resolution, resolution, resolution, -1)
        grid = level.permute(3, 0, 1, 2).unsqueeze(0)  # [1, F, z, y, x]
        sampled = F.grid_sample(
            grid,
            positions.reshape(1, 1, 1, -1, 3).to(table.dtype),
            mode="bilinear",
            padding_mode="border",
            align_corners=True,
        )
        features.append(sampled.reshape(level.shape[-1], -1).T)
    return torch.cat(features, dim=-1)


def march_rays_reference(
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
    """kernels.march_rays without a cell walk: every crossing of a cell plane splits the ray,
    each piece is occupied or not by the cell of its midpoint (outside the cube: empty), and
    samples are placed along the concatenated occupied pieces by a cumulative sum and a search."""
    size = occupancy.shape[0]
    start, direction = (origins - center) / scale, directions / scale
    planes = -1.0 + 2.0 * torch.arange(size + 1, dtype=torch.float32) / size
    with torch.no_grad():
        safe = torch.where(direction == 0, torch.ones_like(direction), direction)
        crossings = (planes[None, None, :] - start[:, :, None]) / safe[:, :, None]
        crossings = torch.where(direction[:, :, None] == 0, t_near[:, None, None], crossings)
    cuts = torch.cat([t_near[:, None], t_far[:, None], crossings.reshape(len(origins), -1)], dim=-1)
    cuts = torch.minimum(torch.maximum(cuts, t_near[:, None]), torch.maximum(t_far, t_near)[:, None])
    cuts = cuts.sort(dim=-1).values
    lengths = cuts[:, 1:] - cuts[:, :-1]
    middles = start[:, None] + 0.5 * (cuts[:, 1:] + cuts[:, :-1])[..., None] * direction[:, None]
    inside = (middles.abs() <= 1.0).all(dim=-1)  # outside the grid's cube counts as empty
    cells = ((middles + 1.0) * size / 2.0).floor().long().clamp(0, size - 1)
    occupied = occupancy.bool()[cells[..., 2], cells[..., 1], cells[..., 0]] & inside & (lengths > 0)
    occupied_lengths = torch.where(occupied, lengths, torch.zeros_like(lengths))
    total = occupied_lengths.double().sum(dim=-1)
    step = torch.clamp(total / max_samples, min=min_step)
    counts = torch.where(total > 0, torch.ceil(total / step - 1e-6).clamp(1, max_samples), torch.zeros_like(total))
    k = torch.arange(max_samples, dtype=torch.float64)
    bin_start = k * step[:, None]
    bin_end = torch.where(k == counts[:, None] - 1, total[:, None], (k + 1) * step[:, None])
    fraction = 0.5 if jitter is None else jitter.double()
    s = bin_start + fraction * (bin_end - bin_start)
    cumulative = occupied_lengths.double().cumsum(dim=-1)
    piece = torch.searchsorted(cumulative, s.contiguous(), right=True).clamp(max=lengths.shape[1] - 1)
    before = cumulative.gather(-1, piece) - occupied_lengths.double().gather(-1, piece)
    t = torch.minimum(cuts.gather(-1, piece).double() + (s - before), cuts.gather(-1, piece + 1).double())
    valid = k < counts[:, None]
    t = torch.where(valid, t, torch.zeros_like(t)).float()
    delta = torch.where(valid, bin_end - bin_start, torch.zeros_like(t, dtype=torch.float64)).float()
    return t, delta, counts.long()
