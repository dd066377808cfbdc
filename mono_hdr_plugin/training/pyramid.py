"""Coarse-to-fine training (`--pyramid-levels`): the training views downscaled by 2^k early in the run.

A step at level k renders 4^k times fewer pixels, so the early steps, where the model learns the
coarse layout and the HDR branch its first exposure mapping, cost a fraction of a full-size one.
The level is a function of the step and the run length alone, so a resumed run continues at the
level the interrupted one would have been at. Each level's images are the area mean of the full
ones (data.loading.downscale_image, as --downscale) and its cameras the matching intrinsics.
"""

import math
from dataclasses import replace

import torch

from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.dataset import View
from mono_hdr_plugin.data.loading import downscale_image, downscaled_camera
from mono_hdr_plugin.training.regions import check_region_training, level_costs

MIN_LEVEL_SIDE = 16
"""Smallest image side a level may have: the D-SSIM loss needs 11 px windows, and fewer pixels teach little."""
AUTOMATIC_FROM_SIDE = 512
"""--pyramid-levels left automatic trains coarse-to-fine from this image side on: at 512 px a 3-level
pyramid gained 5 dB HDR in 10 minutes; at 256 px 2 levels were 8 dB behind at 150 s and +1.3 dB HDR,
-0.6 dB LDR at 600 s (docs/sizes.md), no case for a default."""
AUTOMATIC_COARSEST_SIDE = 128
"""--pyramid-levels left automatic keeps the coarsest level at least this wide: the size whose runs the
built-in scenes were tuned at."""


def automatic_levels(views: list[View], coarse_to_fine_pays: bool) -> int:
    """Levels of an automatic pyramid: for a backbone where it pays (Backbone.coarse_to_fine_pays) and
    views of AUTOMATIC_FROM_SIDE or more, the most that keep the coarsest level's side at or above
    AUTOMATIC_COARSEST_SIDE; else 1."""
    side = min((min(view.camera.width, view.camera.height) for view in views), default=0)
    if not coarse_to_fine_pays or side < AUTOMATIC_FROM_SIDE:
        return 1
    levels = 1
    while side // 2**levels >= AUTOMATIC_COARSEST_SIDE:
        levels += 1
    return levels


def pyramid_level(step: int, run_length: int, levels: int, coarse_share: float) -> int:
    """Level of `step` (0: full size, k: 1/2^k a side): the first `coarse_share` of the run is split
    evenly among levels-1 .. 1, coarsest first; the rest trains at full size."""
    coarse_steps = coarse_share * run_length
    if levels <= 1 or step >= coarse_steps:
        return 0
    return levels - 1 - int(step * (levels - 1) // coarse_steps)


def relative_cost(
    start: int, stop: int, run_length: int, levels: int, coarse_share: float, costs: list[float] | None = None
) -> float:
    """Cost of steps start .. stop-1 of a whole-image backbone in full-size steps: a step at level k
    costs costs[k], by default 4^-k, the share of the pixels it renders (regions.level_costs with
    --region-pixels); pyramid_level's levels, counted per level rather than step by step."""
    coarse_steps = coarse_share * run_length
    if levels <= 1 or coarse_steps <= 0:
        return float(max(stop - start, 0))
    if costs is None:
        costs = [4.0**-level for level in range(levels)]
    cost = 0.0
    for level in range(levels):
        if level == 0:  # from the end of the coarse share on
            first, last = math.ceil(coarse_steps), math.inf
        else:  # pyramid_level: levels - 1 - floor(step * (levels - 1) / coarse_steps) == level
            first = math.ceil((levels - 1 - level) * coarse_steps / (levels - 1))
            last = math.ceil((levels - level) * coarse_steps / (levels - 1))
        cost += max(0, min(stop, last) - max(start, first)) * costs[level]
    return cost


def downscaled_view(view: View, factor: int) -> View:
    """`view` with its photo and HDR area-averaged by `factor` and its camera scaled to match."""
    if factor == 1:
        return view

    def shrink(image: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(downscale_image(image.numpy(), factor, view.name or str(view.view_id)))

    return replace(
        view,
        camera=downscaled_camera(view.camera, factor),
        image=shrink(view.image),
        hdr=None if view.hdr is None else shrink(view.hdr),
    )


class ImagePyramid:
    """The training views at the level a step trains at; only the current level's images are held."""

    def __init__(
        self,
        views: list[View],
        levels: int,
        coarse_share: float,
        whole_images: bool = True,
        region_pixels: int | None = None,
    ):
        check_region_training(region_pixels, whole_images)
        side = min((min(view.camera.width, view.camera.height) for view in views), default=0)
        if levels > 1 and side // 2 ** (levels - 1) < MIN_LEVEL_SIDE:
            most = max(1, (side // MIN_LEVEL_SIDE).bit_length())
            raise FlagError(
                f"--pyramid-levels {levels}: the coarsest level of these {side} px images would be "
                f"{side // 2 ** (levels - 1)} px, under {MIN_LEVEL_SIDE}; use at most --pyramid-levels {most}"
            )
        self.views, self.levels, self.coarse_share = views, levels, coarse_share
        self.whole_images = whole_images
        """The backbone renders whole images (a coarse step costs less) rather than ray batches (the same)."""
        full_pixels = sum(view.camera.width * view.camera.height for view in views) / max(len(views), 1)
        self.level_costs = level_costs(full_pixels, levels, region_pixels)
        """A step's cost at each level in full-size steps (--region-pixels caps the pixels a step renders)."""
        self.level = 0
        self.level_views: dict[int, View] = {}

    def level_at(self, step: int, run_length: int) -> int:
        return pyramid_level(step, run_length, self.levels, self.coarse_share)

    def cost(self, start: int, stop: int, run_length: int) -> float:
        """Cost of steps start .. stop-1 in full-size steps."""
        if not self.whole_images:
            return float(max(stop - start, 0))
        return relative_cost(start, stop, run_length, self.levels, self.coarse_share, self.level_costs)

    def view(self, index: int, level: int) -> View:
        """Training view `index` at `level` (made on first use; a new level drops the previous one's)."""
        if level != self.level:
            self.level, self.level_views = level, {}
        if level == 0:
            return self.views[index]
        if index not in self.level_views:
            self.level_views[index] = downscaled_view(self.views[index], 2**level)
        return self.level_views[index]
