"""Coarse-to-fine training (--pyramid-levels): levels, their images and cameras, resume, both backbones."""

from types import SimpleNamespace

import numpy as np
import pytest
import register_backbone
import torch
from skimage.transform import downscale_local_mean

from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.registry import get_backbone
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import View
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.checkpoints import load_checkpoint
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.pyramid import (
    ImagePyramid,
    automatic_levels,
    downscaled_view,
    pyramid_level,
    relative_cost,
)
from mono_hdr_plugin.training.trainer import Trainer


def make_config(tmp_path, backbone_config, **flags):
    return train_config_for(type(backbone_config))(
        backbone=backbone_config, out=tmp_path / "run", quiet=True, save_renders=False, **flags
    )


def watch_sizes(trainer: Trainer) -> list[tuple[int, int]]:
    """(width, height) of the camera each training step renders with, appended as it trains."""
    sizes: list[tuple[int, int]] = []
    forward = trainer.pipeline.forward

    def spy(camera, *args, **kwargs):
        sizes.append((camera.width, camera.height))
        return forward(camera, *args, **kwargs)

    trainer.pipeline.forward = spy
    return sizes


@pytest.mark.parametrize(
    "levels, share, run, expected",
    [
        (1, 0.5, 6, [0] * 6),
        (3, 0.5, 8, [2, 2, 1, 1, 0, 0, 0, 0]),
        (2, 0.25, 8, [1, 1, 0, 0, 0, 0, 0, 0]),
        (3, 0.6, 10, [2, 2, 2, 1, 1, 1, 0, 0, 0, 0]),
    ],
)
def test_level_schedule(levels, share, run, expected):
    assert [pyramid_level(step, run, levels, share) for step in range(run)] == expected


@pytest.mark.parametrize("factor", [2, 4])
def test_a_level_is_the_area_mean_and_its_camera_projects_to_the_shrunk_pixel(factor):
    width, height = 18, 14  # not multiples of 4: the remainder is cropped, as --downscale does
    camera = Camera(
        look_at(torch.tensor([0.5, -3.0, 1.0]), torch.zeros(3)),
        fx=20.0,
        fy=21.0,
        cx=9.3,
        cy=6.8,
        width=width,
        height=height,
    )
    rng = np.random.default_rng(0)
    image = torch.from_numpy(rng.random((height, width, 3), dtype=np.float32))
    hdr = torch.from_numpy(rng.random((height, width, 3), dtype=np.float32) * 1000)
    small = downscaled_view(View(camera, image, 0.5, 0, "v", hdr=hdr), factor)
    h, w = height // factor, width // factor
    assert (small.camera.width, small.camera.height) == (w, h)
    for full, shrunk in ((image, small.image), (hdr, small.hdr)):
        reference = downscale_local_mean(
            full.numpy()[: h * factor, : w * factor].astype(np.float64), (factor, factor, 1)
        )
        np.testing.assert_allclose(shrunk.numpy(), reference, rtol=1e-5)
    points = torch.tensor([[0.1, 0.2, 0.3], [-0.4, 0.1, -0.2]])
    full_pixels, _ = camera.project(points)
    shrunk_pixels, _ = small.camera.project(points)
    torch.testing.assert_close(shrunk_pixels, full_pixels / factor, atol=1e-5, rtol=0)


def sized_views(*sides: tuple[int, int]) -> list:
    """Stand-ins of views with cameras of these (width, height): all automatic_levels reads."""
    return [SimpleNamespace(camera=SimpleNamespace(width=w, height=h)) for w, h in sides]


@pytest.mark.parametrize(
    "sides, expected",
    [
        ([(16, 16)], 1),
        ([(128, 128)], 1),
        ([(255, 300)], 1),
        ([(256, 256)], 1),  # 2 levels were measured not to pay at 256 px
        ([(511, 511)], 1),
        ([(512, 512)], 3),
        ([(800, 800)], 3),
        ([(1024, 768)], 3),  # the shorter side counts
        ([(1024, 1024), (600, 600)], 3),  # and the smallest view's
        ([(1024, 1024), (400, 400)], 1),
        ([(1024, 1024)], 4),
    ],
)
def test_automatic_levels_from_512_px_keep_the_coarsest_at_128_px_or_more(sides, expected):
    assert automatic_levels(sized_views(*sides), coarse_to_fine_pays=True) == expected


@pytest.mark.parametrize("levels, share", [(1, 0.5), (2, 0.25), (3, 0.5), (3, 0.6), (4, 0.999), (3, 0.0)])
@pytest.mark.parametrize("run_length", [1, 7, 8, 10, 97])
def test_relative_cost_is_the_sum_over_steps_of_their_pixel_share(levels, share, run_length):
    for start in range(0, run_length + 2, 3):
        for stop in range(start, run_length + 4, 2):
            reference = sum(4.0 ** -pyramid_level(step, run_length, levels, share) for step in range(start, stop))
            assert relative_cost(start, stop, run_length, levels, share) == pytest.approx(reference, abs=1e-12)


def test_automatic_levels_leave_backbones_where_it_does_not_pay_at_full_size():
    assert automatic_levels(sized_views((1024, 1024)), coarse_to_fine_pays=False) == 1


@pytest.mark.parametrize(
    "backbone, preset, pays", [("gs", "cpu", True), ("gs", "paper", False), ("nerf", "cpu", False)]
)
def test_where_coarse_to_fine_pays(backbone, preset, pays):
    """3DGS's budgeted cpu recipe (measured at 512 px), not its official recipe nor NeRF's ray batches."""
    backbone_class = get_backbone(backbone)
    scene = register_backbone.make_capture(size=16, views=2)
    assert backbone_class(backbone_class.presets()[preset], scene.scene_info()).coarse_to_fine_pays is pays


def test_automatic_is_off_at_small_sizes(tmp_path, voxel_scene, voxel_backbone_config):
    trainer = Trainer(make_config(tmp_path, voxel_backbone_config, max_steps=3), "voxel-grid", voxel_scene)
    sizes = watch_sizes(trainer)
    trainer.fit()
    assert sizes == [(16, 16)] * 3


@pytest.fixture(scope="module")
def voxel_scene_512():
    return register_backbone.make_capture(size=512, views=2)


@pytest.mark.parametrize(
    "pixel_batch, expected",
    [(None, [(128, 128), (256, 256), (512, 512), (512, 512)]), (64, [(512, 512)] * 4)],
)
def test_automatic_pyramid_at_512_px(
    tmp_path, voxel_scene_512, voxel_backbone_config, monkeypatch, pixel_batch, expected
):
    """Whole-image training starts at 128 px; ray batches are drawn from the full-size views."""
    monkeypatch.setattr(register_backbone.VoxelGridBackbone, "pixel_batch", pixel_batch)
    trainer = Trainer(make_config(tmp_path, voxel_backbone_config, max_steps=4), "voxel-grid", voxel_scene_512)
    sizes = watch_sizes(trainer)
    trainer.fit()
    assert sizes == expected


@pytest.fixture(scope="module")
def voxel_scene_64():
    return register_backbone.make_capture(size=64, views=4)


def test_resuming_mid_pyramid_continues_at_its_level(tmp_path, voxel_scene_64, voxel_backbone_config):
    flags = {"max_steps": 8, "pyramid_levels": 3, "pyramid_share": 0.5}  # steps 0-1 at 16 px, 2-3 at 32, 4-7 at 64
    first = Trainer(make_config(tmp_path, voxel_backbone_config, **flags), "voxel-grid", voxel_scene_64)
    sizes = watch_sizes(first)
    for _ in range(3):
        first.train_step()
    first.save()
    assert sizes == [(16, 16), (16, 16), (32, 32)]
    config = make_config(tmp_path, voxel_backbone_config, resume=True, **flags)
    resumed = Trainer(config, "voxel-grid", voxel_scene_64)
    resumed.restore(load_checkpoint(resumed.checkpoint_path()))
    sizes = watch_sizes(resumed)
    resumed.fit()
    assert resumed.step == 8 and sizes == [(32, 32)] + [(64, 64)] * 4


@pytest.mark.parametrize(
    "side, levels, most",
    [(12, 1, None), (31, 2, 1), (32, 2, None), (20, 2, 1), (100, 4, 3), (128, 4, None), (63, 3, 2)],
)
def test_the_coarsest_level_keeps_16_pixels_a_side(side, levels, most):
    """side // 2^(levels - 1) must be 16 or more; the error names the most levels that keep it."""
    views = sized_views((side + 5, side))  # the shorter side counts
    if most is None:
        ImagePyramid(views, levels, 0.5)
        return
    with pytest.raises(
        FlagError, match=rf"--pyramid-levels {levels}: .* {side} px .* at most --pyramid-levels {most}$"
    ):
        ImagePyramid(views, levels, 0.5)


def test_level_k_is_2_to_the_k_times_smaller():
    camera = Camera(look_at(torch.tensor([0.0, -3.0, 1.0]), torch.zeros(3)), 90.0, 90.0, 64.0, 64.0, 128, 128)
    view = View(camera, torch.rand(128, 128, 3), 0.5, 0, "v")
    pyramid = ImagePyramid([view], 4, 0.5)
    assert [pyramid.view(0, level).camera.width for level in range(4)] == [128, 64, 32, 16]
    assert pyramid.view(0, 3).image.shape == (16, 16, 3)


def test_too_many_levels_for_the_images(tmp_path, voxel_scene_64, voxel_backbone_config):
    config = make_config(tmp_path, voxel_backbone_config, max_steps=8, pyramid_levels=4)
    with pytest.raises(
        FlagError, match=r"--pyramid-levels 4: .* 64 px images would be 8 px.* at most --pyramid-levels 3"
    ):
        Trainer(config, "voxel-grid", voxel_scene_64)


@pytest.mark.parametrize("backbone", ["gs", "nerf"])
def test_two_steps_at_each_level(tmp_path, backbone):
    """The tiny demo at 64 px: levels of 16, 32 and 64 px; a 3DGS budget grows with the pixels."""
    scene = load_scene(DataConfig(scene="demo", resolution=64))
    backbone_class = get_backbone(backbone)
    preset = next(iter(backbone_class.presets().values()))
    config = make_config(tmp_path, preset, max_steps=6, pyramid_levels=3, pyramid_share=4 / 6)
    trainer = Trainer(config, backbone, scene)
    sizes, budgets, losses = watch_sizes(trainer), [], []
    for _ in range(6):
        losses.append(trainer.train_step()["loss"])
        budgets.append(getattr(trainer.backbone, "budget", None))
    assert sizes == [(16, 16)] * 2 + [(32, 32)] * 2 + [(64, 64)] * 2  # NeRF: its rays drawn from those images
    assert np.isfinite(losses).all()
    if backbone == "gs":
        full = trainer.backbone.full_budget
        assert budgets == [full // 16] * 2 + [full // 4] * 2 + [full] * 2
