"""What one training step sees of a view: the whole image, or a batch of its pixels.

A ray-based backbone (NeRF) trains on random pixels of one view. L_hdr divides the rendered and the
true HDR each by its own maximum (methods.base), as the paper does on whole images; on a random
batch that maximum is the batch's, and where a few pixels hold most of the range (a sun of 8
pixels in 16384, a bulb) it jumps by orders of magnitude between batches that hold the source and
batches that miss it. The normalised target of every other pixel jumps with it, and the
HDR branch is trained towards a different image at every step (docs/outdoor.md, "NeRF: the
brightest pixel in every batch, a bounded logit"). So a batch of an HDR view always holds the
view's brightest pixel: its own maximum is then the whole image's, as on a 3DGS render.

A whole-image backbone (3DGS) trains on the whole view, or with --region-pixels on a random crop of it
(training.regions, which says why a crop is not made to cover the brightest pixel).
"""

import torch

from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.data.dataset import View
from mono_hdr_plugin.methods.base import Targets
from mono_hdr_plugin.training.regions import random_region


def brightest_pixel(hdr: torch.Tensor) -> int:
    """Flat index (row * width + col) of the pixel of hdr [H, W, 3] with the largest channel sum."""
    return int(hdr.sum(-1).argmax())


def training_batch(
    view: View, batch_size: int | None, use_hdr: bool, generator: torch.Generator, region_pixels: int | None = None
) -> tuple[Camera, Targets]:
    """The camera and targets of one step: the whole view (batch_size None), or with region_pixels a
    random crop of about that many pixels (Camera.crop; the whole view when it has no more), else
    batch_size random pixels of it (with replacement), the first of them the brightest HDR pixel when
    the HDR is used."""
    hdr = view.hdr if use_hdr else None
    if batch_size is None:
        camera = view.camera
        if region_pixels is None or camera.width * camera.height <= region_pixels:
            return camera, Targets(ldr=view.image, exposure=view.exposure, hdr=hdr)
        left, top, width, height = random_region(camera.width, camera.height, region_pixels, generator)
        box = slice(top, top + height), slice(left, left + width)
        return camera.crop(left, top, width, height), Targets(
            ldr=view.image[box], exposure=view.exposure, hdr=None if hdr is None else hdr[box]
        )
    height, width = view.camera.height, view.camera.width
    flat = torch.randint(0, height * width, (batch_size,), generator=generator)
    if hdr is not None:
        flat[0] = brightest_pixel(hdr)
    rows, cols = flat // width, flat % width
    pixels = torch.stack([cols.float() + 0.5, rows.float() + 0.5], -1)
    return (
        view.camera.with_pixels(pixels),
        Targets(ldr=view.image[rows, cols], exposure=view.exposure, hdr=None if hdr is None else hdr[rows, cols]),
    )
