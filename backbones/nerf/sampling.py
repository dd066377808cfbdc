"""Where along each ray the field is evaluated: box clipping, stratified and importance samples.

Distances t are along unit directions, so they are world-space lengths. All functions here
work on detached geometry (the cameras carry no gradient) and stay finite on degenerate rays:
rays parallel to a face of the box, rays that miss it, and zero-length segments (far = near).
"""

import torch
from torch import Tensor

# Direction components smaller than this count as parallel to the box face: the slab of that
# axis then contains the whole ray or none of it, and no division by (nearly) zero happens.
_PARALLEL = 1e-12
# Stands for an infinite distance in the slab test while keeping every value finite.
_FAR_AWAY = 1e30
# NeRF's floor on the importance weights: an all-zero pdf becomes uniform instead of NaN.
_PDF_FLOOR = 1e-5


def intersect_box(origins: Tensor, directions: Tensor, bounds_min: Tensor, bounds_max: Tensor) -> tuple[Tensor, Tensor]:
    """Entry and exit distances of rays through an axis-aligned box (slab test).

    origins, directions: [N, 3]; bounds_min, bounds_max: [3].
    Returns t_enter, t_exit: [N]; t_exit < t_enter when the ray misses the box, and t_enter
    is negative when the origin is inside it; a ray parallel to a slab gets +-1e30 for it.
    """
    parallel = directions.abs() < _PARALLEL
    safe_directions = torch.where(parallel, torch.ones_like(directions), directions)
    t_lower = (bounds_min - origins) / safe_directions
    t_upper = (bounds_max - origins) / safe_directions
    inside_slab = (origins >= bounds_min) & (origins <= bounds_max)
    far_away = torch.full_like(t_lower, _FAR_AWAY)
    axis_enter = torch.where(parallel, torch.where(inside_slab, -far_away, far_away), torch.minimum(t_lower, t_upper))
    axis_exit = torch.where(parallel, torch.where(inside_slab, far_away, -far_away), torch.maximum(t_lower, t_upper))
    return axis_enter.amax(dim=-1), axis_exit.amin(dim=-1)


def ray_segments(
    origins: Tensor, directions: Tensor, near: float, far: float, bounds: tuple[Tensor, Tensor] | None
) -> tuple[Tensor, Tensor]:
    """The [t_near, t_far] each ray is sampled in: [near, far], clipped to the box if given.

    origins, directions: [N, 3]. Returns t_near, t_far: [N] with near <= t_near <= t_far;
    rays that miss the box get a zero-length segment (t_far = t_near), so they render empty.
    """
    t_near = torch.full(origins.shape[:1], float(near), dtype=origins.dtype, device=origins.device)
    t_far = torch.full_like(t_near, float(far))
    if bounds is not None:
        t_enter, t_exit = intersect_box(origins, directions, *bounds)
        t_near = torch.maximum(t_near, t_enter)
        t_far = torch.minimum(t_far, t_exit)
    return t_near, torch.maximum(t_far, t_near)


def sample_stratified(t_near: Tensor, t_far: Tensor, num_samples: int, perturb: bool) -> Tensor:
    """NeRF's stratified samples: evenly spaced from t_near to t_far, jittered within their bins.

    t_near, t_far: [N]. Returns [N, num_samples], sorted, inside [t_near, t_far]; without
    `perturb` the first sample is at t_near and the last at t_far.
    """
    steps = torch.linspace(0.0, 1.0, num_samples, dtype=t_near.dtype, device=t_near.device)
    t = t_near[:, None] + (t_far - t_near)[:, None] * steps
    if perturb and num_samples > 1:
        mids = 0.5 * (t[:, 1:] + t[:, :-1])
        upper = torch.cat([mids, t[:, -1:]], dim=-1)
        lower = torch.cat([t[:, :1], mids], dim=-1)
        t = lower + (upper - lower) * torch.rand_like(t)
    return t


def sample_pdf(bin_edges: Tensor, weights: Tensor, num_samples: int, deterministic: bool) -> Tensor:
    """Inverse-transform samples of the piecewise-constant pdf given by `weights` on the bins.

    bin_edges: [N, B + 1] sorted; weights: [N, B] >= 0 (need not sum to 1; all-zero gives a
    uniform pdf). deterministic: evenly spaced quantiles (evaluation) instead of random ones.
    Returns [N, num_samples], sorted, inside [bin_edges[:, 0], bin_edges[:, -1]].
    """
    weights = weights + _PDF_FLOOR
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    cdf = cdf.clamp(max=1.0)
    shape = (weights.shape[0], num_samples)
    if deterministic:
        quantiles = torch.linspace(0.0, 1.0, num_samples, dtype=cdf.dtype, device=cdf.device).expand(shape)
    else:
        quantiles = torch.rand(shape, dtype=cdf.dtype, device=cdf.device).sort(dim=-1).values
    quantiles = quantiles.contiguous()
    above = torch.searchsorted(cdf, quantiles, right=True).clamp(max=cdf.shape[-1] - 1)
    below = (above - 1).clamp(min=0)
    cdf_below, cdf_above = cdf.gather(-1, below), cdf.gather(-1, above)
    edge_below, edge_above = bin_edges.gather(-1, below), bin_edges.gather(-1, above)
    span = cdf_above - cdf_below
    # A bin of (floored) zero probability has span 0: put the sample at its lower edge.
    fraction = torch.where(span > 0, (quantiles - cdf_below) / torch.where(span > 0, span, 1.0), 0.0)
    return edge_below + fraction.clamp(0.0, 1.0) * (edge_above - edge_below)


# Share of the resampling pdf spread evenly over a ray's occupied length: stretches that look
# empty still get a sample now and then, so their density keeps being trained.
_UNIFORM_SHARE = 0.01


def resample_occupied(
    t: Tensor, delta: Tensor, fraction: Tensor, weights: Tensor, count: int, deterministic: bool
) -> tuple[Tensor, Tensor]:
    """`count` samples per ray drawn from the rendering weights of marched samples.

    t, delta: [N, S] marched samples (kernels.march_rays): sample k sits at t[:, k] and stands for
    the k-th bin, of length delta[:, k], of the ray's occupied length; fraction [N, S]: where in its
    bin each sits; weights [N, S] >= 0 their rendering weights. The pdf lives on the occupied
    length: 99 % from the weights, 1 % spread evenly. Returns t, delta [N, count]: each new sample
    stands for the occupied length up to the next one (the last: up to the end), so the deltas of
    a ray add up to the part of its occupied length from its first sample on; rays without
    occupied length get delta 0 everywhere.
    """
    edges = torch.cat([torch.zeros_like(delta[:, :1]), torch.cumsum(delta, dim=-1)], dim=-1)
    total = edges[:, -1:]
    mass = weights.sum(dim=-1, keepdim=True).clamp_min(torch.finfo(weights.dtype).tiny)
    pdf = (1.0 - _UNIFORM_SHARE) * weights / mass + _UNIFORM_SHARE * delta / total.clamp_min(
        torch.finfo(delta.dtype).tiny
    )
    # Evenly spaced quantiles end at the ray's end, where a sample would stand for no length: draw
    # one more and drop it.
    s = (
        sample_pdf(edges, pdf, count + 1, deterministic=True)[:, :-1]
        if deterministic
        else sample_pdf(edges, pdf, count, deterministic=False)
    )
    bins = torch.searchsorted(edges[:, 1:].contiguous(), s.contiguous(), right=True).clamp(max=delta.shape[1] - 1)
    s_marched = edges.gather(1, bins) + fraction.gather(1, bins) * delta.gather(1, bins)
    t_new = t.gather(1, bins) + (s - s_marched)
    delta_new = torch.diff(torch.cat([s, total], dim=-1), dim=-1).clamp_min(0.0)
    return t_new, delta_new
