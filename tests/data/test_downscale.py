"""--downscale on every layout: images and HDR area-averaged, intrinsics scaled with the image."""

import numpy as np
import pytest
import torch
from test_layouts import HEIGHT, POINT, WIDTH, make_scene

from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.layouts import writable_layouts, write_layout
from mono_hdr_plugin.data.loading import load_scene


def block_mean(image: torch.Tensor, factor: int) -> np.ndarray:
    """Independent area average: the whole factor x factor blocks, remainder cropped."""
    pixels = image.numpy().astype(np.float64)
    height, width = pixels.shape[0] // factor, pixels.shape[1] // factor
    return pixels[: height * factor, : width * factor].reshape(height, factor, width, factor, 3).mean((1, 3))


@pytest.mark.parametrize("factor", [2, 3])
@pytest.mark.parametrize("layout", writable_layouts())
def test_downscale_on_every_layout(tmp_path, layout, factor):
    write_layout(make_scene(), tmp_path / layout, layout)
    full = load_scene(DataConfig(data=tmp_path / layout))
    small = load_scene(DataConfig(data=tmp_path / layout, downscale=factor))
    assert len(small.train) == len(full.train) and len(small.test) == len(full.test)
    for big, view in zip(full.train + full.test, small.train + small.test):
        assert view.stem == big.stem
        assert (view.camera.width, view.camera.height) == (WIDTH // factor, HEIGHT // factor)
        assert view.image.shape == (HEIGHT // factor, WIDTH // factor, 3)
        np.testing.assert_allclose(view.image.numpy(), block_mean(big.image, factor), rtol=1e-5, atol=1e-6)
        if big.hdr is not None:  # hdr-nerf-real, llff and nerfstudio have no HDR ground truth
            np.testing.assert_allclose(view.hdr.numpy(), block_mean(big.hdr, factor), rtol=1e-5)
        # A world point lands on the downscaled pixel of its full-size projection (pixel edges at integers).
        full_pixel, _ = big.camera.project(POINT)
        small_pixel, _ = view.camera.project(POINT)
        torch.testing.assert_close(small_pixel, full_pixel / factor, atol=1e-4, rtol=0)
        assert view.camera.fx == pytest.approx(big.camera.fx / factor)
    assert any(view.hdr is not None for view in small.train) == (layout in ("hdr-gs", "hdr-nerf-synthetic"))
