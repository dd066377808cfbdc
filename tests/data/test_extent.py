"""Whether a scene is unbounded, decided from its photos: the plane sweep on scenes drawn analytically
(a textured wall, a textured sky at infinity), and every published layout on the studio's scenes."""

import json
import math

import pytest
import torch

from mono_hdr_plugin.apps.studio.commands import SynthConfig, synth
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.data import extent
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.extent import (
    AT_INFINITY_DISPARITY,
    decide_extent,
    grey_at_working_size,
    partners_of,
    sweep_match,
    sweep_projections,
)
from mono_hdr_plugin.data.loading import load_scene

SIZE = 96
WALL_DEPTH = 3.0
"""Distance (along +y) from the cameras' line to the wall."""


def texture(u: torch.Tensor, v: torch.Tensor, seed: int, frequency: float) -> torch.Tensor:
    """A smooth, never-repeating grey texture in [0.1, 0.9]: a sum of random waves."""
    generator = torch.Generator().manual_seed(seed)
    value = torch.zeros_like(u)
    for _ in range(12):
        heading = torch.rand(1, generator=generator).item() * 2 * math.pi
        scale = frequency * (0.5 + torch.rand(1, generator=generator).item())
        phase = torch.rand(1, generator=generator).item() * 2 * math.pi
        value = value + torch.cos(scale * (math.cos(heading) * u + math.sin(heading) * v) + phase)
    return 0.5 + 0.4 * torch.tanh(value / 3)


def camera_at(x: float) -> Camera:
    focal = SIZE / (2 * math.tan(math.radians(30)))
    eye = torch.tensor([x, 0.0, 0.0])
    return Camera(look_at(eye, eye + torch.tensor([0.0, 1.0, 0.0])), focal, focal, SIZE / 2, SIZE / 2, SIZE, SIZE)


def wall_hit(origins: torch.Tensor, directions: torch.Tensor, depth: float) -> torch.Tensor:
    """Where rays meet the wall y = depth."""
    return origins + ((depth - origins[..., 1]) / directions[..., 1])[..., None] * directions


def photograph(camera: Camera, sky: bool, gain: float = 1.0, stripes: float | None = None) -> torch.Tensor:
    """[H, W, 3] photo: below the horizon a wall at y = WALL_DEPTH (textured, or vertical stripes of
    period `stripes` metres); above it a sky that depends on the ray's direction only (at infinity)
    when `sky`, else a textured wall three times further."""
    origins, directions = camera.rays()
    near = wall_hit(origins, directions, WALL_DEPTH)
    if stripes is None:
        lower = texture(near[..., 0], near[..., 2], seed=1, frequency=12.0)
    else:
        lower = 0.5 + 0.4 * torch.cos(2 * math.pi * near[..., 0] / stripes)
    if sky:
        upper = texture(directions[..., 0] / directions[..., 1], directions[..., 2] / directions[..., 1], 2, 25.0)
    else:
        far = wall_hit(origins, directions, 3 * WALL_DEPTH)
        upper = texture(far[..., 0], far[..., 2], seed=3, frequency=8.0)
    grey = torch.where(directions[..., 2] > 0, upper, lower) * gain
    return grey[..., None].expand(SIZE, SIZE, 3).clamp(0, 1)


def rig(xs, sky: bool):
    cameras = [camera_at(x) for x in xs]
    # Alternate gains: photos at different exposures must still match (normalised correlation).
    images = [photograph(c, sky, gain=0.8 + 0.2 * (i % 2)) for i, c in enumerate(cameras)]
    return images, cameras


class TestSweepProjections:
    def test_infinity_is_the_direction_and_a_finite_distance_the_point(self):
        reference, other = camera_at(0.0), camera_at(0.4)
        xy, in_front = sweep_projections(reference, other, torch.tensor([0.0, 1 / WALL_DEPTH]))
        origins, directions = reference.rays()
        far, _ = other.project(origins.reshape(-1, 3) + 1e6 * directions.reshape(-1, 3))
        torch.testing.assert_close(xy[0].reshape(-1, 2), far, atol=1e-3, rtol=0)
        near, _ = other.project((origins + WALL_DEPTH * directions).reshape(-1, 3))
        torch.testing.assert_close(xy[1].reshape(-1, 2), near, atol=1e-3, rtol=0)
        assert in_front.all()


class TestSweepMatch:
    def test_sky_at_infinity_wall_at_its_disparity(self):
        images, cameras = rig([0.0, 0.3], sky=True)
        grey = [grey_at_working_size(image, camera) for image, camera in zip(images, cameras)]
        match = sweep_match(*grey[0], *grey[1])
        rows = torch.arange(SIZE)[:, None].expand(SIZE, SIZE)
        sky, wall = match.confident & (rows < SIZE / 2 - 4), match.confident & (rows > SIZE / 2 + 4)
        assert sky.sum() > 0.1 * SIZE * SIZE and wall.sum() > 0.1 * SIZE * SIZE
        assert (match.disparity[sky] <= AT_INFINITY_DISPARITY).float().mean() > 0.95
        expected = cameras[0].fx * 0.3 / WALL_DEPTH  # f b / depth: 24.9 px
        assert (match.disparity[wall] - expected).abs().median() < 1.0
        assert not match.at_infinity()[wall].any()

    def test_no_baseline_tells_nothing(self):
        images, cameras = rig([0.0, 0.0], sky=True)
        grey = [grey_at_working_size(image, camera) for image, camera in zip(images, cameras)]
        assert not sweep_match(*grey[0], *grey[1]).confident.any()


class TestPartners:
    def test_widest_and_half_baseline_among_cameras_looking_the_same_way(self):
        cameras = [camera_at(x) for x in (0.0, 0.1, 0.2, 0.3, 0.4)]
        turned = Camera(look_at(torch.tensor([5.0, 0, 0]), torch.tensor([5.0, -1, 0])), 50, 50, 48, 48, 96, 96)
        assert partners_of(0, [*cameras, turned]) == [4, 2]
        assert partners_of(0, [cameras[0], turned]) == []


class TestDecideExtent:
    XS = [0.05 * i for i in range(9)]

    def test_open_sky_is_unbounded(self):
        decision = decide_extent(*rig(self.XS, sky=True))
        assert decision.unbounded and decision.pairs >= 4, decision.reason
        assert "unbounded" in decision.reason

    def test_closed_view_is_bounded(self):
        decision = decide_extent(*rig(self.XS, sky=False))
        assert not decision.unbounded and decision.pairs >= 4, decision.reason

    def test_periodic_texture_beyond_the_sweep_does_not_alias_to_infinity(self, monkeypatch):
        """Stripes on a near wall that move two periods, further than the sweep looks, line up again
        at the rotation-only position (a checkered floor did this): the second partner, at a
        third of the baseline, sees them at their disparity and overrules the first."""
        monkeypatch.setattr(extent, "SWEEP_DISPARITY", 16.0)
        monkeypatch.setattr(extent, "SWEEP_STEPS", 17)
        focal = camera_at(0.0).fx
        period_px, baseline = 20.0, 40.0 * WALL_DEPTH / focal  # 2 periods of disparity on the near wall
        cameras = [camera_at(x) for x in (0.0, 0.3 * baseline, baseline)]
        images = [photograph(c, sky=False, stripes=period_px * WALL_DEPTH / focal) for c in cameras]
        reference, widest = (grey_at_working_size(images[i], cameras[i]) for i in (0, 2))
        first_partner_only = extent.sweep_match(*reference, *widest)
        lower = torch.arange(SIZE)[:, None].expand(SIZE, SIZE) > SIZE / 2 + 4
        assert first_partner_only.at_infinity()[lower].sum() > 200  # the alias this test is about
        assert not decide_extent(images, cameras).unbounded

    def test_one_photo_is_bounded(self):
        images, cameras = rig([0.0], sky=True)
        assert not decide_extent(images, cameras).unbounded


class TestLoadScene:
    def test_forcing_overrides_the_studio(self, tiny_demo):
        assert not load_scene(DataConfig(scene="demo")).metadata["unbounded"]
        forced = load_scene(DataConfig(scene="demo", extent="unbounded"))
        assert forced.metadata["unbounded"] and "--extent unbounded" in forced.metadata["extent_reason"]


@pytest.mark.slow
class TestEveryLayout:
    """Studio scenes at their real size, written in every published layout without anything that
    says whether they are unbounded, load as their content says; an interior whose transforms
    declare it unbounded (aabb_scale 16) loads as bounded, and the reason says so."""

    @pytest.mark.parametrize("layout", ["hdr-nerf-synthetic", "hdr-gs", "hdr-nerf-real", "llff", "nerfstudio"])
    @pytest.mark.parametrize("scene", ["backlit-sun", "sky-horizon", "demo", "lamp-room"])
    def test_layout_decides_as_the_content_says(self, tmp_path, layout, scene):
        synth(SynthConfig(scene=scene, out=tmp_path / "data", layout=layout))
        if layout == "hdr-nerf-synthetic":
            for split in ("train", "test"):  # drop the declaration `synth` writes for outdoor scenes
                path = tmp_path / "data" / f"transforms_{split}.json"
                path.write_text(
                    json.dumps({k: v for k, v in json.loads(path.read_text()).items() if k != "aabb_scale"})
                )
        loaded = load_scene(DataConfig(data=tmp_path / "data"))
        truth = load_scene(DataConfig(scene=scene)).metadata["unbounded"]
        assert loaded.metadata["unbounded"] is truth, loaded.metadata["extent_reason"]
        assert "declares" not in loaded.metadata["extent_reason"]  # no field, no claim to overrule

    def test_metadata_that_lies_is_overruled(self, tmp_path):
        synth(SynthConfig(scene="demo", out=tmp_path / "data", layout="hdr-nerf-synthetic"))
        for split in ("train", "test"):
            path = tmp_path / "data" / f"transforms_{split}.json"
            path.write_text(json.dumps({**json.loads(path.read_text()), "aabb_scale": 16}))
        loaded = load_scene(DataConfig(data=tmp_path / "data"))
        assert not loaded.metadata["unbounded"]
        assert "declares it unbounded" in loaded.metadata["extent_reason"]
