"""Lens distortion removed with COLMAP's camera models (pycolmap), for process-data and the readers.

A photo taken through a lens with distortion is resampled onto a pinhole camera: for every pixel
of the pinhole image, pycolmap's `img_from_cam` of the distorted camera says where that ray landed
in the photo, and the photo is sampled there (bilinear). The distortion formulas are COLMAP's
(OPENCV, FULL_OPENCV, OPENCV_FISHEYE, ...), never written out here.
"""

import functools

import numpy as np
import torch

from mono_hdr_plugin.data.captures import ImageSource

PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")


def pinhole_grid(distorted, pinhole, offset: tuple[int, int] = (0, 0)) -> torch.Tensor | None:
    """[1, H, W, 2] grid_sample coordinates: where each pixel of the pinhole camera lies in the photo;
    `offset` is the (left, top) of a pinhole image cut from a larger one.

    None when the photo is the image (no distortion, no cut). COLMAP's pixel (0, 0) covers [0, 1]^2,
    grid_sample's (align_corners=False) covers [-1, -1 + 2 / W], so x_grid = 2 x / W - 1.
    """
    same_size = (distorted.width, distorted.height) == (pinhole.width, pinhole.height)
    if distorted.model.name in PINHOLE_MODELS and same_size:
        return None
    rows, cols = np.mgrid[0 : pinhole.height, 0 : pinhole.width].astype(np.float64) + 0.5
    if distorted.model.name in PINHOLE_MODELS:  # only cut: the window's pixels, shifted
        pixels = np.stack([cols.ravel() + offset[0], rows.ravel() + offset[1]], -1)
    else:
        rays = pinhole.cam_from_img(np.stack([cols.ravel(), rows.ravel()], -1))
        pixels = distorted.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], -1), check_cheirality=False)
    grid = pixels / np.array([distorted.width, distorted.height]) * 2 - 1
    return torch.from_numpy(grid.reshape(1, pinhole.height, pinhole.width, 2)).float()


def remap(image: np.ndarray, grid: torch.Tensor | None) -> np.ndarray:
    """Bilinear resampling of float [H, W, 3] pixels (LDR or linear HDR) onto the pinhole camera."""
    if grid is None:
        return image
    pixels = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)[None]
    sampled = torch.nn.functional.grid_sample(pixels, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[0].permute(1, 2, 0).numpy()


@functools.lru_cache(maxsize=4)
def _same_intrinsics_grid(model: str, width: int, height: int, params: tuple[float, ...]) -> torch.Tensor | None:
    """The grid of a distorted camera onto the pinhole camera of its own fx, fy, cx, cy and size (cached:
    the views of one camera share it, and a 12-megapixel grid takes a second to project)."""
    import pycolmap

    distorted = pycolmap.Camera(model=model, width=width, height=height, params=list(params))
    pinhole = pycolmap.Camera(model="PINHOLE", width=width, height=height, params=list(params[:4]))
    return pinhole_grid(distorted, pinhole)


def undistorted_source(source: ImageSource, model: str, width: int, height: int, params: list[float]) -> ImageSource:
    """`source`'s photo, taken with the COLMAP camera `model` (params fx, fy, cx, cy, then its distortion),
    resampled when called onto the pinhole camera with the same fx, fy, cx, cy and size (OpenCV's
    `undistort` default): a reader keeps its intrinsics and only the pixels move."""

    def read() -> np.ndarray:
        return remap(source(), _same_intrinsics_grid(model, width, height, tuple(float(p) for p in params)))

    return read
