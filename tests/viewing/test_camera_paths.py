"""Viewer cameras (viser's convention) and camera paths, against poses known by construction."""

import math

import numpy as np
import pytest
import torch
import viser.transforms as vtf

from mono_hdr_plugin.apps.camera_paths import (
    ViewerCamera,
    camera_from_viewer,
    camera_path,
    focus_point,
    scene_up,
    viewer_from_camera,
)
from mono_hdr_plugin.core.cameras import look_at
from mono_hdr_plugin.training.evaluation import first_per_camera


class TestViewerCamera:
    def test_identity_pose_projects_as_opencv(self):
        """viser: +z forward, +y down, +x right in the camera. A point right of the axis lands right
        of the centre, one below lands below, one on the edge of the vertical field of view on
        the bottom row."""
        fov = math.radians(60.0)
        camera = camera_from_viewer(ViewerCamera((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), fov, 1.5), 40, 0.1, 10.0)
        assert (camera.width, camera.height) == (60, 40)
        points = torch.tensor([[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 5.0], [0.0, 5.0 * math.tan(fov / 2), 5.0]])
        pixels, depth = camera.project(points)
        torch.testing.assert_close(pixels[0], torch.tensor([30.0, 20.0]))
        assert pixels[1, 0] > 30.0 and pixels[1, 1] == pytest.approx(20.0)
        assert pixels[2, 1] > 20.0 and pixels[2, 0] == pytest.approx(30.0)
        assert pixels[3, 1].item() == pytest.approx(40.0, abs=1e-4)
        torch.testing.assert_close(depth, torch.full((4,), 5.0))

    def test_known_pose_from_the_viewer_library(self):
        """A camera at (3, -4, 2) looking at the origin, z up: viser's own SO3 makes the quaternion
        the browser would send; the converted camera has exactly that camera-to-world."""
        expected = look_at(torch.tensor([3.0, -4.0, 2.0]), torch.zeros(3))
        wxyz = vtf.SO3.from_matrix(expected[:3, :3].double().numpy()).wxyz
        camera = camera_from_viewer(ViewerCamera(tuple(wxyz), (3.0, -4.0, 2.0), 0.8, 1.0), 32, 0.1, 10.0)
        torch.testing.assert_close(camera.c2w, expected, atol=1e-6, rtol=0)
        pixels, depth = camera.project(torch.zeros(1, 3))  # the target is in the middle of the image
        torch.testing.assert_close(pixels[0], torch.tensor([16.0, 16.0]), atol=1e-4, rtol=0)
        assert depth.item() == pytest.approx(math.sqrt(29.0))

    def test_round_trip(self, voxel_scene):
        camera = voxel_scene.test[1].camera
        view = viewer_from_camera(camera)
        again = camera_from_viewer(view, camera.height, camera.near, camera.far)
        torch.testing.assert_close(again.c2w, camera.c2w, atol=1e-6, rtol=0)
        assert again.fy == pytest.approx(camera.fy) and again.width == camera.width

    def test_bad_field_of_view_is_refused(self):
        with pytest.raises(ValueError, match="field of view"):
            camera_from_viewer(ViewerCamera((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0, 1.0), 10, 0.1, 1.0)


class TestPaths:
    def test_rig_geometry(self, voxel_scene):
        cameras = [v.camera for v in voxel_scene.train]
        torch.testing.assert_close(focus_point(voxel_scene, cameras), torch.zeros(3), atol=1e-5, rtol=0)
        assert scene_up(cameras) @ torch.tensor([0.0, 0.0, 1.0]) > 0.9  # the rig has z up

    def test_dataset_path_spreads_the_cameras(self, voxel_scene):
        views = first_per_camera(voxel_scene.test)
        assert [c.center.tolist() for c in camera_path("dataset", voxel_scene, voxel_scene.test, None)] == [
            v.camera.center.tolist() for v in views
        ]
        two = camera_path("dataset", voxel_scene, voxel_scene.test, 2)
        assert torch.equal(two[0].c2w, views[0].camera.c2w) and torch.equal(two[1].c2w, views[-1].camera.c2w)

    def test_interpolation_starts_and_ends_on_dataset_cameras(self, voxel_scene):
        views = first_per_camera(voxel_scene.train)
        path = camera_path("interpolate", voxel_scene, voxel_scene.train, 13)
        assert len(path) == 13
        torch.testing.assert_close(path[0].c2w, views[0].camera.c2w, atol=1e-5, rtol=0)
        torch.testing.assert_close(path[-1].c2w, views[-1].camera.c2w, atol=1e-5, rtol=0)
        # 13 frames over 3 segments: frame 4 sits exactly on the second camera
        torch.testing.assert_close(path[4].c2w, views[1].camera.c2w, atol=1e-5, rtol=0)

    def test_spiral_of_a_ring_rig_orbits_the_focus(self, voxel_scene):
        path = camera_path("spiral", voxel_scene, voxel_scene.train, 16)
        assert len(path) == 16
        distances = torch.stack([c.center.norm() for c in path])
        torch.testing.assert_close(distances, torch.full((16,), 2.6 * math.hypot(1, 0.8 / 2.6)), atol=1e-3, rtol=0)
        for camera in path:  # every frame looks straight at the focus (the origin)
            pixel, _ = camera.project(torch.zeros(1, 3))
            torch.testing.assert_close(pixel[0], torch.tensor([camera.cx, camera.cy]), atol=1e-3, rtol=0)
        azimuths = np.unwrap([math.atan2(c.center[1], c.center[0]) for c in path])
        assert abs(azimuths[-1] - azimuths[0]) > 1.5 * math.pi  # most of a full circle

    def test_spiral_of_forward_facing_cameras_circles_in_front(self, voxel_scene):
        """Cameras on a small patch all looking at the origin: the spiral stays near them."""
        from dataclasses import replace

        views = [
            replace(
                voxel_scene.train[0],
                camera=replace(voxel_scene.train[0].camera, c2w=look_at(torch.tensor([3.0, dx, dz]), torch.zeros(3))),
            )
            for dx, dz in ((0.0, 0.0), (0.3, 0.0), (0.0, 0.3), (-0.3, -0.2))
        ]
        views = [replace(v, view_id=i) for i, v in enumerate(views)]
        path = camera_path("spiral", voxel_scene, views, 12)
        assert all(abs(c.center[0].item() - 3.0) < 0.3 and c.center[1:].norm() < 0.6 for c in path)

    def test_bad_requests(self, voxel_scene):
        with pytest.raises(ValueError, match="--frames"):
            camera_path("spiral", voxel_scene, voxel_scene.train, 0)
        with pytest.raises(ValueError, match="--path 'zoom'"):
            camera_path("zoom", voxel_scene, voxel_scene.train, 5)
        with pytest.raises(ValueError, match="at least two cameras"):
            camera_path("interpolate", voxel_scene, voxel_scene.train[:1], 5)
