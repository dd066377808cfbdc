"""Outdoor studio scenes: a sky at infinity where it was put, a sun that clips, the unbounded flag."""

import json

import numpy as np
import pytest
import torch

from mono_hdr_plugin.apps.studio import outdoor
from mono_hdr_plugin.apps.studio.commands import SynthConfig, synth
from mono_hdr_plugin.apps.studio.dataset import studio_captured_scene
from mono_hdr_plugin.apps.studio.render import dynamic_range, render_scene
from mono_hdr_plugin.apps.studio.scene import STUDIO_EXPOSURES, CameraRig, StudioScene
from mono_hdr_plugin.apps.studio.scenes import BUILTIN_SCENES, SCENES
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene

REAL = {scene.name: scene for scene in BUILTIN_SCENES}
OUTDOOR = ("backlit-sun", "sky-horizon")
SUNS = {"backlit-sun": outdoor.BACKLIT_SUN, "sky-horizon": outdoor.CLOUDY_SUN}


def sun_pixel(camera, sun: np.ndarray) -> tuple[float, float] | None:
    """Where the direction `sun` projects (x, y in pixels), from the camera's own projection of a point
    very far along it; None when it lies behind the camera or outside the image."""
    far_point = torch.tensor(camera.center.double().numpy() + 1e6 * sun, dtype=torch.float32)[None]
    pixel, depth = camera.project(far_point)
    x, y = pixel[0].tolist()
    inside = depth.item() > 0 and 0 <= x < camera.width and 0 <= y < camera.height
    return (x, y) if inside else None


class TestSkyDirections:
    def test_map_centre_column_and_rows(self):
        """Mitsuba's lat-long: the top row is the zenith, the middle rows the horizon, u = 0.5 is local
        +z, which ENVMAP_TO_WORLD turns into world -y."""
        directions = outdoor.sky_directions((8, 4))
        assert np.allclose(np.linalg.norm(directions, axis=-1), 1.0)
        assert (directions[0, :, 2] > 0.9).all() and (directions[-1, :, 2] < -0.9).all()
        assert np.allclose(directions[1:3, :, 2], [[np.cos(3 * np.pi / 8)], [np.cos(5 * np.pi / 8)]])
        between = directions[1:3, 3:5].mean((0, 1))  # around u = 0.5 at the horizon
        assert np.allclose(between / np.linalg.norm(between), [0, -1, 0], atol=1e-6)

    def test_sun_lands_where_its_direction_projects(self, studio_cache):
        """A sun in an otherwise black sky, rendered by Mitsuba: its brightest pixel is the pixel the
        camera projects the sun's direction to (the map's axis convention and ENVMAP_TO_WORLD agree)."""
        sun = outdoor.direction(95.0, 8.0)

        def content() -> dict:
            directions = outdoor.sky_directions((256, 128))
            return {"sky": outdoor.envmap(outdoor.sun_disc(directions, sun, (100.0, 100.0, 100.0), 2.0))}

        scene = StudioScene(
            name="sun-only",
            description="",
            content=content,
            resolution=(40, 30),
            spp=9,
            rig=CameraRig(target=(0.0, 3.0, 0.5), radius=3.0, azimuth_deg=(-110, -70), elevation_deg=(0, 5), views=3),
        )
        render = render_scene(scene, use_cache=False)
        for camera, image in zip(scene.cameras(), render.radiance):
            expected = sun_pixel(camera, sun)
            assert expected is not None
            row, col = np.unravel_index(image.sum(-1).argmax(), image.shape[:2])
            assert abs(col + 0.5 - expected[0]) <= 1.0 and abs(row + 0.5 - expected[1]) <= 1.0


class TestUnbounded:
    def test_only_scenes_with_a_sky_are_unbounded(self):
        assert {scene.name for scene in BUILTIN_SCENES if scene.unbounded()} == set(OUTDOOR)

    @pytest.mark.parametrize("name", ["backlit-sun", "demo"])
    def test_scene_info_carries_the_flag(self, name):
        data = load_scene(DataConfig(scene=name))
        assert data.scene_info().unbounded == (name in OUTDOOR)

    def test_views_that_see_the_sky_have_a_far_plane_beyond_the_ground(self):
        scene = SCENES["backlit-sun"]
        captured, render = studio_captured_scene(scene), render_scene(scene)
        for view, hit in zip(captured.views, render.hit):
            assert not hit.all()  # every view sees sky
            assert np.isfinite(view.camera.far) and view.camera.far >= 999 * view.camera.near

    def test_initial_points_lie_on_surfaces(self):
        """No point in the sky: each one is a position a pixel hit (sky pixels hold none)."""
        scene = SCENES["backlit-sun"]
        captured, render = studio_captured_scene(scene), render_scene(scene)
        surfaces = {tuple(p) for p in render.positions[render.hit].astype(np.float32)}
        assert len(captured.points) > 0
        assert all(tuple(p) in surfaces for p in captured.points.numpy())

    @pytest.mark.parametrize("name", ["backlit-sun", "demo"])
    def test_declaration_survives_the_hdr_nerf_synthetic_layout(self, tmp_path, name):
        """Written as instant-ngp's aabb_scale and read back as a declaration; whether the folder loads
        as unbounded is its photos' call (tests/data/test_extent.py, at the scenes' real size)."""
        out = synth(SynthConfig(scene=name, out=tmp_path / name, layout="hdr-nerf-synthetic"))
        transforms = json.loads((out / "transforms_train.json").read_text())
        assert transforms.get("aabb_scale", 1) == (16 if name in OUTDOOR else 1)
        assert load_scene(DataConfig(data=out)).metadata["declared_unbounded"] is (True if name in OUTDOOR else None)


@pytest.mark.slow
class TestOutdoorScenesFull:
    @pytest.mark.parametrize("name", OUTDOOR)
    def test_dynamic_range_at_least_1e5(self, name):
        assert dynamic_range(render_scene(REAL[name]).radiance) >= 1e5

    @pytest.mark.parametrize("name", OUTDOOR)
    def test_sun_at_its_pixel_and_clipped_at_every_exposure(self, name):
        """In every view the sun's direction projects into the frame, and the brightest pixel of the view
        lies within 2 px of that projection (the post of backlit-sun hides part of the disc in two views,
        never all of it), and its photo is white at t1..t5."""
        from mono_hdr_plugin.apps.studio.capture import capture

        scene = REAL[name]
        render = render_scene(scene)
        for camera, image in zip(scene.cameras(), render.radiance):
            expected = sun_pixel(camera, SUNS[name])
            assert expected is not None
            row, col = np.unravel_index(image.mean(-1).argmax(), image.shape[:2])
            assert abs(col + 0.5 - expected[0]) <= 2.0 and abs(row + 0.5 - expected[1]) <= 2.0
            for exposure in STUDIO_EXPOSURES:
                assert (
                    capture(image[row, col][None, None], exposure, ("exposure", "crf", "clip"), scene.capture).min()
                    == 1
                )
