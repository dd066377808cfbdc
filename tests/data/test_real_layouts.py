"""LLFF and nerfstudio layouts: read as published (hand-written files), written by synth, bad input named.

Expected values are written by hand or from the published formulas (OpenCV's distortion models),
never computed with the code under test.
"""

import json
import math

import numpy as np
import pytest
import torch
from test_layouts import make_scene

from mono_hdr_plugin.apps.studio.commands import SynthConfig, synth
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError, MissingFileError
from mono_hdr_plugin.data.io import write_png
from mono_hdr_plugin.data.layouts import detect_layout, read_layout, write_layout
from mono_hdr_plugin.data.loading import load_scene

# LLFF columns (down, right, back) of a camera whose down is world -z and right is world -y: it looks
# along world +x (right x down = forward), so back is world -x.
LOOKING_ALONG_X = [[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]


def llff_row(centre, columns=LOOKING_ALONG_X, hwf=(12, 16, 20), near=0.5, far=9.0) -> list[float]:
    """One poses_bounds.npy row written out by hand: 3x5 [down right back centre hwf], near, far."""
    pose = np.zeros((3, 5))
    pose[:, :3] = np.array(columns).T
    pose[:, 3], pose[:, 4] = centre, hwf
    return [*pose.ravel(), near, far]


def make_llff(folder, views=9, size=(16, 12), downscaled=(4,)):
    """An LLFF scene: images/ with IMG_<n>.JPG-like names, images_N/ (as minify writes, PNG), poses_bounds.npy."""
    rng = np.random.default_rng(1)
    for index in range(views):
        write_png(folder / "images" / f"IMG_{4026 + index}.png", rng.random((size[1], size[0], 3)))
        for factor in downscaled:
            small = np.full((size[1] // factor, size[0] // factor, 3), 0.25, np.float32)
            write_png(folder / f"images_{factor}" / f"IMG_{4026 + index}.png", small)
    np.save(folder / "poses_bounds.npy", np.array([llff_row([index, 2.0, 3.0]) for index in range(views)]))
    return folder


class TestLlff:
    def test_pose_looks_where_the_columns_say(self, tmp_path):
        scene = read_layout(make_llff(tmp_path / "llff"))
        camera = scene.views[0].camera
        np.testing.assert_allclose(camera.c2w[:3, 2].numpy(), [1, 0, 0], atol=1e-6)  # forward = -back
        np.testing.assert_allclose(camera.c2w[:3, 0].numpy(), [0, -1, 0], atol=1e-6)  # right
        np.testing.assert_allclose(camera.c2w[:3, 1].numpy(), [0, 0, -1], atol=1e-6)  # down
        np.testing.assert_allclose(camera.c2w[:3, 3].numpy(), [0, 2, 3], atol=1e-6)
        pixels, depth = camera.project(torch.tensor([[10.0, 2.0, 3.0], [10.0, 1.0, 3.0], [10.0, 2.0, 2.0]]))
        assert depth[0].item() == pytest.approx(10)
        assert pixels[0].tolist() == pytest.approx([8, 6])  # straight ahead: the principal point
        assert pixels[1, 0] > 8 and pixels[1, 1] == pytest.approx(6)  # world -y is to the right
        assert pixels[2, 1] > 6 and pixels[2, 0] == pytest.approx(8)  # world -z is down

    def test_every_eighth_view_held_out_bounds_kept_exposures_learned(self, tmp_path):
        scene = read_layout(make_llff(tmp_path / "llff", views=17))
        assert [v.view_id for v in scene.views if v.split == "test"] == [0, 8, 16]
        assert {(v.camera.near, v.camera.far) for v in scene.views} == {(0.5, 9.0)}
        assert scene.views[0].camera.fx == pytest.approx(20)  # hwf focal at the photos' width
        assert scene.metadata["unknown_exposures"] == [f"IMG_{4026 + i}.png" for i in range(17)]
        assert [v.name for v in scene.views][:2] == ["IMG_4026", "IMG_4027"]

    def test_downscale_reads_images_n(self, tmp_path):
        folder = make_llff(tmp_path / "llff")
        data = load_scene(DataConfig(data=folder, downscale=4))
        view = data.train[0]
        assert tuple(view.image.shape) == (3, 4, 3)
        assert torch.allclose(view.image, torch.tensor(0.25), atol=1 / 255)  # images_4's pixels, not an average
        assert view.camera.fx == pytest.approx(5) and (view.camera.width, view.camera.height) == (4, 3)

    def test_downscale_without_images_n_averages(self, tmp_path):
        folder = make_llff(tmp_path / "llff")
        full = load_scene(DataConfig(data=folder)).train[0].image.numpy()
        half = load_scene(DataConfig(data=folder, downscale=2)).train[0].image.numpy()
        np.testing.assert_allclose(half, full.reshape(6, 2, 8, 2, 3).mean((1, 3)), atol=1e-6)

    def test_rounded_images_n_keeps_its_size(self, tmp_path):
        """Mip-NeRF 360's images_4 rounds (4946 px / 4 = 1237): 18 x 10 photos, 5 x 3 copies at factor 4."""
        folder = make_llff(tmp_path / "llff", size=(18, 10), downscaled=())
        for index in range(9):
            write_png(folder / "images_4" / f"IMG_{4026 + index}.png", np.zeros((3, 5, 3)))
        view = load_scene(DataConfig(data=folder, downscale=4)).train[0]
        assert (view.camera.width, view.camera.height) == (5, 3) and tuple(view.image.shape) == (3, 5, 3)

    def test_detected_before_the_colmap_model_beside_it(self, tmp_path):
        folder = make_llff(tmp_path / "llff")
        (folder / "sparse" / "0").mkdir(parents=True)  # imgs2poses leaves COLMAP's model in the scene
        assert detect_layout(folder) == "llff"

    def test_exposure_file_makes_it_hdr_nerf_real(self, tmp_path):
        """HDR-NeRF real is LLFF with exposures: its poses_bounds_exps.npy decides, even beside poses_bounds.npy."""
        folder = make_llff(tmp_path / "llff")
        np.save(folder / "poses_bounds_exps.npy", np.zeros((9, 18)))
        assert detect_layout(folder) == "hdr-nerf-real"

    @pytest.mark.parametrize(
        "damage, message",
        [
            (lambda rows: rows[:, :15], r"poses_bounds.npy: shape \(9, 15\), expected \(images, 17\)"),
            (lambda rows: rows[:8], r"poses_bounds.npy: 8 rows but .*images has 9 images.*regenerate"),
            (lambda rows: np.where(np.arange(17) == 3, np.nan, rows), r"poses_bounds.npy: .*NaN or Inf"),
        ],
    )
    def test_bad_poses_file_is_named(self, tmp_path, damage, message):
        folder = make_llff(tmp_path / "llff")
        np.save(folder / "poses_bounds.npy", damage(np.load(folder / "poses_bounds.npy")))
        with pytest.raises(DatasetError, match=message):
            read_layout(folder)

    def test_incomplete_images_n_is_named(self, tmp_path):
        folder = make_llff(tmp_path / "llff")
        (folder / "images_4" / "IMG_4030.png").unlink()
        with pytest.raises(DatasetError, match=r"images_4: 8 images but .*images has 9; regenerate images_4/"):
            read_layout(folder)


def ramp(width: int, height: int) -> np.ndarray:
    """A photo whose red and green are its own pixel-centre coordinates x / W and y / H: bilinear
    resampling of it returns the position it sampled, exactly (a linear function)."""
    rows, cols = np.mgrid[0:height, 0:width] + 0.5
    return np.stack([cols / width, rows / height, np.zeros_like(cols)], -1)


def opencv_distort(x, y, k1=0.0, k2=0.0, k3=0.0, p1=0.0, p2=0.0):
    """OpenCV's (and nerfstudio's) perspective distortion of normalised coordinates, as published."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def fisheye_distort(x, y, k1=0.0, k2=0.0, k3=0.0, k4=0.0):
    """OpenCV's fisheye (equidistant) model: theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)."""
    r = np.hypot(x, y)
    theta = np.arctan(r)
    theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
    scale = np.divide(theta_d, r, out=np.ones_like(r), where=r > 0)  # theta_d / r -> 1 at the centre
    return x * scale, y * scale


W, H = 40, 30
SHARED = {"camera_model": "OPENCV", "w": W, "h": H, "fl_x": 30.0, "fl_y": 32.0, "cx": 19.5, "cy": 15.5}
SHARED_DISTORTION = {"k1": -0.2, "k2": 0.05, "k3": 0.02, "p1": 0.003, "p2": -0.002}
# frame_2 has its own focal length, principal point and radial distortion (per-frame intrinsics).
OWN = {"fl_x": 28.0, "cx": 20.5, "k1": 0.1, "k2": 0.0, "k3": 0.0}


def write_transforms(folder, shared=None, frames=None, **extra):
    """A transforms.json as ns-process-data writes it, with ramp photos in images/."""
    folder.mkdir(parents=True, exist_ok=True)
    shared = {**SHARED, **SHARED_DISTORTION} if shared is None else shared
    if frames is None:
        frames = [{"file_path": f"images/frame_{n:05d}.png", "transform_matrix": np.eye(4).tolist()} for n in (1, 2, 3)]
        frames[1].update(OWN)
        frames[2]["transform_matrix"][0][3] = 1.5  # one step along world +x
    for frame in frames:
        write_png(folder / frame["file_path"], ramp(W, H), bits=16)
    (folder / "transforms.json").write_text(json.dumps({**shared, **extra, "frames": frames}))
    return folder


def sampled_positions(image: np.ndarray) -> np.ndarray:
    """Where in the photo each pixel of an undistorted ramp was sampled, in pixels."""
    return np.stack([image[..., 0] * W, image[..., 1] * H], -1)


def expected_positions(distort, fx, fy, cx, cy, **coefficients) -> np.ndarray:
    rows, cols = np.mgrid[0:H, 0:W] + 0.5
    xd, yd = distort((cols - cx) / fx, (rows - cy) / fy, **coefficients)
    return np.stack([fx * xd + cx, fy * yd + cy], -1)


def assert_positions(got: np.ndarray, expected: np.ndarray) -> None:
    """Within 0.01 px wherever the sampled point lies inside the photo (outside, it is clamped)."""
    inside = (expected[..., 0] > 0.5) & (expected[..., 0] < W - 0.5)
    inside &= (expected[..., 1] > 0.5) & (expected[..., 1] < H - 0.5)
    assert inside.mean() > 0.7
    np.testing.assert_allclose(got[inside], expected[inside], atol=0.01)


class TestNerfstudio:
    def test_hand_written_file_read_unchanged(self, tmp_path):
        scene = read_layout(write_transforms(tmp_path / "ns", test_filenames=["images/frame_00002.png"]))
        assert detect_layout(tmp_path / "ns") == "nerfstudio"
        first, own, moved = scene.views
        assert (first.camera.fx, first.camera.fy, first.camera.cx, first.camera.cy) == (30, 32, 19.5, 15.5)
        assert (own.camera.fx, own.camera.fy, own.camera.cx, own.camera.cy) == (28, 32, 20.5, 15.5)
        assert (first.camera.width, first.camera.height) == (W, H)
        # OpenGL identity (looking down world -z, y up) is OpenCV's x right, y down, z forward = world -z.
        np.testing.assert_allclose(first.camera.c2w.numpy(), np.diag([1.0, -1.0, -1.0, 1.0]))
        np.testing.assert_allclose(moved.camera.c2w[:3, 3].numpy(), [1.5, 0, 0])
        assert [v.split for v in scene.views] == ["train", "test", "train"]
        assert scene.metadata["unknown_exposures"] == [f"images/frame_0000{n}.png" for n in (1, 2, 3)]
        assert_positions(
            sampled_positions(first.shots[0].image()),
            expected_positions(opencv_distort, 30, 32, 19.5, 15.5, **SHARED_DISTORTION),
        )
        own_distortion = {**SHARED_DISTORTION, "k1": 0.1, "k2": 0.0, "k3": 0.0}
        assert_positions(
            sampled_positions(own.shots[0].image()),
            expected_positions(opencv_distort, 28, 32, 20.5, 15.5, **own_distortion),
        )

    def test_fisheye_undistorted(self, tmp_path):
        fisheye = {"k1": 0.05, "k2": -0.01, "k3": 0.002, "k4": -0.001}
        shared = {**SHARED, "camera_model": "OPENCV_FISHEYE", **fisheye}
        view = read_layout(write_transforms(tmp_path / "ns", shared=shared)).views[0]
        assert_positions(
            sampled_positions(view.shots[0].image()), expected_positions(fisheye_distort, 30, 32, 19.5, 15.5, **fisheye)
        )

    def test_pinhole_photo_is_not_resampled(self, tmp_path):
        view = read_layout(write_transforms(tmp_path / "ns", shared={**SHARED, "camera_model": "PINHOLE"})).views[0]
        np.testing.assert_allclose(view.shots[0].image(), ramp(W, H), atol=1e-4)

    def test_instant_ngp_camera_angle_and_image_size(self, tmp_path):
        """instant-ngp may give only camera_angle_x and leave w, h to the photos."""
        shared = {"camera_angle_x": 2 * math.atan(20 / 25)}
        view = read_layout(write_transforms(tmp_path / "ns", shared=shared)).views[0]
        assert view.camera.fx == pytest.approx(25) and view.camera.fy == pytest.approx(25)
        assert (view.camera.cx, view.camera.cy, view.camera.width) == (20, 15, W)

    def test_every_eighth_frame_held_out_without_lists(self, tmp_path):
        frames = [
            {"file_path": f"images/frame_{n:05d}.png", "transform_matrix": np.eye(4).tolist()} for n in range(1, 11)
        ]
        scene = read_layout(write_transforms(tmp_path / "ns", shared=SHARED, frames=frames))
        assert [v.view_id for v in scene.views if v.split == "test"] == [0, 8]

    def test_train_filenames_leave_the_rest_to_test(self, tmp_path):
        scene = read_layout(
            write_transforms(tmp_path / "ns", train_filenames=["./images/frame_00001.png", "images/frame_00003.png"])
        )
        assert [v.split for v in scene.views] == ["train", "test", "train"]

    def test_ply_points_and_applied_transform(self, tmp_path):
        from plyfile import PlyData, PlyElement

        folder = tmp_path / "ns"
        applied = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]  # ns-process-data's COLMAP -> z-up
        write_transforms(folder, ply_file_path="sparse_pc.ply", applied_transform=applied)
        vertices = np.array(
            [(1.0, 2.0, 3.0, 255, 0, 0), (-1.0, 0.5, 2.0, 0, 255, 0)],
            [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
        )
        PlyData([PlyElement.describe(vertices, "vertex")]).write(str(folder / "sparse_pc.ply"))
        scene = read_layout(folder)
        assert scene.points.tolist() == [[1, 2, 3], [-1, 0.5, 2]]
        assert scene.point_colors.tolist() == [[1, 0, 0], [0, 1, 0]]
        assert scene.metadata["applied_transform"] == applied

    def test_synthetic_hdr_nerf_is_not_nerfstudio(self, tmp_path):
        folder = write_transforms(tmp_path / "ns")
        (folder / "transforms.json").rename(folder / "transforms_train.json")
        assert detect_layout(folder) == "hdr-nerf-synthetic"

    @pytest.mark.parametrize(
        "change, error, message",
        [
            ({"camera_model": "EQUIRECTANGULAR"}, DatasetError, r"transforms.json: frames\[0\]: camera_model "),
            ({"k4": 0.01}, DatasetError, r"frames\[0\]: k4 = 0.01 with camera_model OPENCV"),
            ({"test_filenames": ["images/nope.png"]}, DatasetError, r"test_filenames names images/nope.png"),
            ({"fl_x": float("nan")}, DatasetError, r"frames\[0\].fl_x must be"),
        ],
    )
    def test_bad_values_are_named(self, tmp_path, change, error, message):
        with pytest.raises(error, match=message):
            read_layout(write_transforms(tmp_path / "ns", shared={**SHARED, **change}))

    def test_missing_photo_is_named(self, tmp_path):
        folder = write_transforms(tmp_path / "ns")
        (folder / "images" / "frame_00002.png").unlink()
        with pytest.raises(MissingFileError, match=r"frame_00002.png: file not found; restore the photo or remove"):
            read_layout(folder)

    def test_size_other_than_w_h_is_named(self, tmp_path):
        with pytest.raises(DatasetError, match=r"w, h = 41.0, 30.0 but .*frame_00001.png is 40x30"):
            read_layout(write_transforms(tmp_path / "ns", shared={**SHARED, "w": 41}))


class TestSynthRealLayouts:
    @pytest.mark.parametrize("layout", ["llff", "nerfstudio"])
    def test_studio_scene_round_trip(self, tmp_path, tiny_demo, layout, monkeypatch):
        from mono_hdr_plugin.apps.studio import scenes
        from mono_hdr_plugin.apps.studio.dataset import studio_captured_scene

        monkeypatch.setitem(scenes.SCENES, "demo", tiny_demo)
        out = synth(SynthConfig(scene="demo", out=tmp_path / layout, layout=layout))
        assert detect_layout(out) == layout
        original, loaded = studio_captured_scene(tiny_demo, seed=0), read_layout(out)
        assert len(loaded.views) == len(original.views) == 10
        for a, b in zip(original.views, loaded.views):
            torch.testing.assert_close(b.camera.c2w, a.camera.c2w, atol=1e-5, rtol=0)
            assert (b.camera.fx, b.camera.cx, b.camera.width) == pytest.approx(
                (a.camera.fx, a.camera.cx, a.camera.width)
            )
            assert np.array_equal(b.shots[0].image(), a.shots[len(a.shots) // 2].image())  # the middle exposure
        splits = [v.split for v in loaded.views]
        if layout == "llff":
            assert [i for i, split in enumerate(splits) if split == "test"] == [0, 8]
        else:
            assert splits == [v.split for v in original.views]


class TestWriteIsAllOrNothing:
    @pytest.mark.parametrize("layout", ["llff", "nerfstudio"])
    def test_failed_write_leaves_no_detectable_dataset(self, tmp_path, layout):
        """The file that makes a folder a dataset (poses_bounds.npy, transforms.json) is written last."""
        scene = make_scene(views=3)

        def unreadable():
            raise OSError("disk unplugged")

        scene.views[2].shots[2].image = unreadable
        with pytest.raises(OSError, match="disk unplugged"):
            write_layout(scene, tmp_path / layout, layout)
        with pytest.raises(DatasetError, match="unknown dataset layout"):
            detect_layout(tmp_path / layout)
