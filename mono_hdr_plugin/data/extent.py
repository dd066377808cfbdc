"""Whether a scene reaches to infinity (an open sky), decided from its photos and poses.

Content at infinity moves between two photos by the camera's rotation alone: its image in the second
photo is where the first photo's ray direction projects, whatever the baseline. Content at a finite
depth moves further, by its disparity. A plane sweep in inverse depth (`infinity_evidence`) finds,
for every textured pixel of a training photo, the inverse depth at which a partner photo matches it
best (zero-mean normalised cross-correlation of small patches: blind to the exposure and response
differences between the photos); a pixel whose match is distinct and lies within a pixel of the
rotation-only position, in a pair with tens of pixels of parallax elsewhere, is at infinity.

Nothing here reads metadata: every layout (and a layout whose metadata lies) is decided the same way.
docs/outdoor.md, "When a scene counts as unbounded", gives the figures behind the thresholds.
"""

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from mono_hdr_plugin.core.cameras import Camera

WORKING_SIDE = 160
"""Long side, in pixels, the photos are compared at: enough for clouds, a sun and a horizon."""
SWEEP_DISPARITY = 40.0
"""Largest disparity the sweep tries, in working pixels (at the median pixel)."""
SWEEP_STEPS = 41
"""Inverse-depth hypotheses, infinity first: a pixel of disparity a step."""
PATCH = 7
"""Side of the matched patches, in working pixels."""
MIN_TEXTURE = 0.004
"""Least standard deviation of a patch (photo values in [0, 1]) to take part: below, noise matches."""
MIN_CORRELATION = 0.9
"""Least correlation of the best match."""
MIN_DISTINCTNESS = 0.1
"""How much better the best match must be than every hypothesis 3 or more steps from it."""
AT_INFINITY_DISPARITY = 1.0
"""A match within this many working pixels of the rotation-only position is at infinity..."""
AT_INFINITY_RELATIVE = 0.1
"""... or within this fraction of the pair's parallax (10 times further than the near content):
poses from structure from motion are a fraction of a degree off, which moves infinity a pixel or two."""
MIN_PARALLAX = 8.0
"""A pair whose finite matches move less than this (90th percentile, working pixels) cannot tell
infinity from the scene's far side, and is not counted."""
UNBOUNDED_SHARE = 0.01
"""A scene is unbounded when this share of its confidently matched pixels (mean over the pairs) is
at infinity. Measured (docs/outdoor.md): the six studio interiors 0.00 % in every pair; the outdoor
scenes 8.7 % (backlit-sun: a smooth sky, only the sun and its aureole match) and 55 % (sky-horizon's
clouds); opensfm_lund, a real street, 2.4 %."""
MIN_MATCHED = 0.01
"""A pair that matches under this fraction of its pixels confidently (a blank photo) is not counted."""
REFERENCE_VIEWS = 6
"""Training photos compared, each with its best partner: a few seconds at the working size."""


@dataclass(frozen=True)
class PairEvidence:
    """What one pair of photos says: the fraction of the reference photo's pixels matched at infinity
    and at a finite depth, and the pair's parallax (90th percentile disparity of the finite ones)."""

    at_infinity: float
    finite: float
    parallax: float


@dataclass(frozen=True)
class ExtentDecision:
    """Whether the scene is unbounded, and the sentence the training log prints about it."""

    unbounded: bool
    share_at_infinity: float
    pairs: int
    reason: str


def grey_at_working_size(image: Tensor, camera: Camera) -> tuple[Tensor, Camera]:
    """[H, W, 3] photo -> [h, w] grey photo whose long side is at most WORKING_SIDE, and its camera."""
    factor = max(1, math.ceil(max(camera.width, camera.height) / WORKING_SIDE))
    grey = image.float().mean(-1)[None, None]
    if factor > 1:
        grey = F.avg_pool2d(grey, factor)
    height, width = grey.shape[-2:]
    small = camera.scaled(1.0 / factor)
    return grey[0, 0], Camera(
        c2w=camera.c2w, fx=small.fx, fy=small.fy, cx=small.cx, cy=small.cy, width=width, height=height
    )


def _patch_statistics(image: Tensor) -> tuple[Tensor, Tensor]:
    """Mean and standard deviation of every PATCH x PATCH window of [N, 1, H, W] images."""
    mean = F.avg_pool2d(image, PATCH, stride=1, padding=PATCH // 2, count_include_pad=False)
    square = F.avg_pool2d(image * image, PATCH, stride=1, padding=PATCH // 2, count_include_pad=False)
    return mean, (square - mean * mean).clamp_min(0.0).sqrt()


def sweep_projections(reference: Camera, other: Camera, inverse_depths: Tensor) -> tuple[Tensor, Tensor]:
    """Where each reference pixel lands in `other` if it lies at each inverse distance along its ray.

    Returns ([K, H, W, 2] pixel coordinates, [K, H, W] whether the point is in front of `other`). The
    point at inverse distance w is o + d / w (d the unit ray direction); times w it is w o + d, so
    w = 0 (infinity) is the direction d itself and needs no special case.
    """
    origins, directions = reference.rays()
    rotation = other.w2c[:3, :3].float()
    offset = (origins[0, 0] - other.center.float()) @ rotation.T
    camera = directions @ rotation.T  # [H, W, 3]
    points = camera[None] + inverse_depths[:, None, None, None] * offset  # [K, H, W, 3]
    depth = points[..., 2]
    safe = torch.where(depth > 1e-6, depth, torch.ones_like(depth))
    xy = torch.stack([other.fx * points[..., 0] / safe + other.cx, other.fy * points[..., 1] / safe + other.cy], -1)
    return xy, depth > 1e-6


@dataclass(frozen=True)
class SweepMatch:
    """The plane sweep of a reference photo against a partner: which pixels matched confidently, how
    far (working pixels) each best match lies from the rotation-only position, and the pair's
    parallax (90th percentile of those distances over the confident pixels)."""

    confident: Tensor
    disparity: Tensor
    parallax: float

    def at_infinity(self) -> Tensor:
        limit = max(AT_INFINITY_DISPARITY, AT_INFINITY_RELATIVE * self.parallax)
        return self.confident & (self.disparity <= limit)


def _correlations(reference_image: Tensor, other_image: Tensor, xy: Tensor, valid: Tensor) -> Tensor:
    """[K, H, W] zero-mean normalised cross-correlation of each reference patch with the partner's
    patch around `xy` [K, H, W, 2] (-1 where not `valid` or either patch is untextured)."""
    height, width = other_image.shape
    grid = torch.stack([2 * xy[..., 0] / width - 1, 2 * xy[..., 1] / height - 1], -1)
    source = other_image[None, None].expand(xy.shape[0], 1, height, width)
    warped = F.grid_sample(source, grid, mode="bilinear", padding_mode="border", align_corners=False)
    ref = reference_image[None, None]
    ref_mean, ref_std = _patch_statistics(ref)
    warped_mean, warped_std = _patch_statistics(warped)
    covariance = F.avg_pool2d(warped * ref, PATCH, stride=1, padding=PATCH // 2, count_include_pad=False)
    covariance = covariance - warped_mean * ref_mean
    usable = (ref_std > MIN_TEXTURE) & (warped_std > MIN_TEXTURE) & valid[:, None]
    correlation = covariance / (ref_std * warped_std).clamp_min(1e-12)
    return torch.where(usable, correlation, torch.tensor(-1.0))[:, 0]


def sweep_match(reference_image: Tensor, reference: Camera, other_image: Tensor, other: Camera) -> SweepMatch:
    """The plane sweep of one pair (grey photos at working size and their cameras): see the module."""
    height, width = reference_image.shape
    nothing = SweepMatch(torch.zeros(height, width, dtype=torch.bool), torch.zeros(height, width), 0.0)
    unit = sweep_projections(reference, other, torch.tensor([0.0, 1.0]))[0]
    median_shift = (unit[1] - unit[0]).norm(dim=-1).median().item()
    if not math.isfinite(median_shift) or median_shift < 1e-6:
        return nothing  # no baseline: nothing can be told from infinity
    inverse_depths = torch.linspace(0.0, SWEEP_DISPARITY / median_shift, SWEEP_STEPS)
    xy, in_front = sweep_projections(reference, other, inverse_depths)
    margin = PATCH // 2 + 1  # a patch that reaches past either photo's edge compares padding
    valid = in_front & (xy >= margin).all(-1) & (xy[..., 0] <= other.width - margin)
    valid &= xy[..., 1] <= other.height - margin
    valid[:, :margin] = valid[:, -margin:] = valid[:, :, :margin] = valid[:, :, -margin:] = False
    correlation = _correlations(reference_image, other_image, xy, valid)
    best_score, best = correlation.max(0)
    far_from_best = (torch.arange(SWEEP_STEPS)[:, None, None] - best[None]).abs() >= 3
    runner_up = torch.where(far_from_best, correlation, torch.tensor(-1.0)).max(0).values
    disparities = (xy - xy[:1]).norm(dim=-1)  # [K, H, W]
    # Near the epipole every depth lands within a pixel or two: such pixels cannot tell.
    sweeps_far = disparities[-1] >= MIN_PARALLAX
    confident = sweeps_far & (best_score > MIN_CORRELATION) & (best_score - runner_up > MIN_DISTINCTNESS)
    if confident.sum() < 20:
        return nothing
    disparity = disparities.gather(0, best[None])[0]
    return SweepMatch(confident, disparity, torch.quantile(disparity[confident], 0.9).item())


def infinity_evidence(reference: tuple[Tensor, Camera], partners: list[tuple[Tensor, Camera]]) -> PairEvidence:
    """What a reference photo (grey at working size, camera) says against two partners at different
    baselines: a pixel is at infinity when both sweeps put it there (a periodic texture beyond the
    sweep's range aliases to a different disparity in each, and one partner may not see it at all),
    finite when the first puts it elsewhere."""
    matches = [sweep_match(*reference, *partner) for partner in partners]
    first = matches[0]
    at_infinity = first.at_infinity()
    for other in matches[1:]:
        at_infinity &= other.at_infinity()
    finite = first.confident & ~first.at_infinity()
    pixels = first.confident.numel()
    return PairEvidence(at_infinity.sum().item() / pixels, finite.sum().item() / pixels, first.parallax)


def partners_of(index: int, cameras: list[Camera]) -> list[int]:
    """Two cameras that see most of what camera `index` sees (viewing directions within 20 degrees of
    its own): the widest baseline, and the one whose baseline is nearest half of it. Empty when
    no other camera looks the same way."""
    forward = cameras[index].c2w[:3, 2].float()
    baselines = {
        other: (camera.center - cameras[index].center).norm().item()
        for other, camera in enumerate(cameras)
        if other != index and torch.dot(forward, camera.c2w[:3, 2].float()).item() >= math.cos(math.radians(20))
    }
    if len(baselines) < 2:
        return []
    widest = max(baselines, key=baselines.__getitem__)
    half = min((o for o in baselines if o != widest), key=lambda o: abs(baselines[o] - baselines[widest] / 2))
    return [widest, half]


def decide_extent(images: list[Tensor], cameras: list[Camera]) -> ExtentDecision:
    """Unbounded or not, from training photos ([H, W, 3] in [0, 1]) and their cameras (module doc)."""
    if len(cameras) < 2:
        return ExtentDecision(False, 0.0, 0, "bounded: one photo cannot show parallax")
    references = sorted({round(i * (len(cameras) - 1) / max(1, REFERENCE_VIEWS - 1)) for i in range(REFERENCE_VIEWS)})
    small = [grey_at_working_size(image, camera) for image, camera in zip(images, cameras, strict=True)]
    evidence = []
    for index in references:
        partners = partners_of(index, cameras)
        if not partners:
            continue
        pair = infinity_evidence(small[index], [small[other] for other in partners])
        if pair.parallax >= MIN_PARALLAX and pair.at_infinity + pair.finite >= MIN_MATCHED:
            evidence.append(pair)
    if not evidence:
        return ExtentDecision(
            False, 0.0, 0, "bounded: no pair of training photos has the parallax to tell a far side from infinity"
        )
    share = sum(pair.at_infinity / (pair.at_infinity + pair.finite) for pair in evidence) / len(evidence)
    unbounded = share >= UNBOUNDED_SHARE
    return ExtentDecision(
        unbounded,
        share,
        len(evidence),
        f"{'unbounded' if unbounded else 'bounded'}: {100 * share:.1f} % of the confidently matched pixels of "
        f"{len(evidence)} training photos lie at infinity (a sky; threshold {100 * UNBOUNDED_SHARE:.0f} %)",
    )
