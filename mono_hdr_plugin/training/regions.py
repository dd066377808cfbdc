"""Region training (`--region-pixels`): a 3DGS step renders and scores a random crop of the view.

A whole-image step costs about its pixel count (39 ms at 128 px, 1677 ms at 800 px, CPU rasteriser),
so on large views a step that renders a crop of a fixed pixel budget costs the same at any image size.
The crop is a camera of its own (Camera.crop: the principal point shifted by the crop's offset, the
whole image's size kept as its `frame`), so the rasteriser culls every Gaussian that cannot touch it,
and its targets are the same pixels of the photo and of the HDR (L_prior's target is computed from the
cropped photo afterwards, by the trainer).

Where the crop goes: uniformly at random, every position equally likely, from the trainer's generator
(a run is repeatable, a resumed run continues the sequence). The NeRF batch always holds the view's
brightest HDR pixel (training.batches) because L_hdr divides each side by its own maximum; a crop is
not made to cover it. Always covering it would train only the part of the view around it (a crop of a
quarter of the image never reaches the far corners), and covering it only sometimes changes nothing for
the other crops, which are normalised by their own maxima either way. The normalisation is the same on
both sides of L_hdr, so a render proportional to the truth scores zero on every crop: crops pull towards
the same HDR, with steps weighted differently, as the pyramid's levels do. Curves decide whether that
costs HDR on scenes with a small very bright source (docs/sizes.md).

The pyramid composes with it: a level is downscaled first and cropped second, and a level whose image
holds fewer pixels than the budget trains whole. A step's cost in full-size steps (the run-length
estimate, training.hooks) is then min(level pixels, region) / min(full pixels, region) (`level_costs`).
"""

import math

import torch

from mono_hdr_plugin.core.validation import FlagError

MIN_REGION_PIXELS = 121
"""The smallest --region-pixels: 11 x 11, the window of the D-SSIM loss."""


def region_size(width: int, height: int, region_pixels: int) -> tuple[int, int]:
    """(w, h) of the crop of a width x height image: about sqrt(region_pixels) a side, clamped to the
    image; a side clamped short gives its pixels to the other side (a narrow image still gets about
    region_pixels). An image of region_pixels or fewer is its own crop (trains whole)."""
    if width * height <= region_pixels:
        return width, height
    crop_width = min(width, round(math.sqrt(region_pixels)))
    crop_height = min(height, round(region_pixels / crop_width))
    crop_width = min(width, round(region_pixels / crop_height))
    return crop_width, crop_height


def random_region(width: int, height: int, region_pixels: int, generator: torch.Generator) -> tuple[int, int, int, int]:
    """(left, top, w, h) of a crop of region_size, at a uniformly random position inside the image."""
    crop_width, crop_height = region_size(width, height, region_pixels)
    left = int(torch.randint(0, width - crop_width + 1, (1,), generator=generator))
    top = int(torch.randint(0, height - crop_height + 1, (1,), generator=generator))
    return left, top, crop_width, crop_height


def level_costs(full_pixels: float, levels: int, region_pixels: int | None) -> list[float]:
    """Cost of a step at each pyramid level in full-size steps: a level k image holds 4^-k of the
    full pixels, and a step renders min(those, region_pixels) of them (all of them without regions)."""
    if region_pixels is None:
        return [4.0**-level for level in range(levels)]
    full = min(full_pixels, region_pixels)
    return [min(full_pixels * 4.0**-level, region_pixels) / full for level in range(levels)]


def check_region_training(region_pixels: int | None, whole_images: bool) -> None:
    """Refuse --region-pixels for a backbone that trains on ray batches (NeRF): its step already
    renders a fixed number of pixels, so a crop would only narrow what a batch can draw from."""
    if region_pixels is not None and not whole_images:
        raise FlagError(
            f"--region-pixels {region_pixels}: this backbone trains on random ray batches, whose cost does "
            "not grow with the image; region training crops whole-image renders (3DGS): leave it out"
        )
