"""Camera-path videos, EXR sequences and exposure sweeps: frame counts, sizes, brightness."""

import imageio.v2 as imageio
import numpy as np
import pytest
import register_backbone  # noqa: F401 - registers voxel-grid for the command line

from mono_hdr_plugin.apps.camera_paths import camera_path
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.apps.render import ev_sheet, even_sized, render_exposure_sweep, render_path
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import read_exr, read_image
from mono_hdr_plugin.data.loading import load_scene


def video_frames(path) -> list[np.ndarray]:
    with imageio.get_reader(path) as reader:
        return [frame for frame in reader]  # noqa: C416 - list(reader) sizes itself by len(), inf for ffmpeg


class TestPathVideo:
    def test_frame_count_size_and_exr_sequence(self, voxel_mono, tmp_path):
        cameras = camera_path("spiral", voxel_mono.scene, voxel_mono.scene.train, 7)
        render_path(voxel_mono, cameras, tmp_path / "spiral.mp4", output="hdr-filmic", exr_folder=tmp_path / "exr")
        frames = video_frames(tmp_path / "spiral.mp4")
        assert len(frames) == 7 and all(f.shape == (16, 16, 3) for f in frames)
        exrs = sorted((tmp_path / "exr").glob("frame_*_hdr.exr"))
        assert [p.name for p in exrs] == [f"frame_{i:05d}_hdr.exr" for i in range(7)]
        expected = voxel_mono.pipeline.render(cameras[3], 0.5).hdr
        np.testing.assert_allclose(read_exr(exrs[3]), expected.numpy(), rtol=1e-6, atol=1e-7)
        assert not list(tmp_path.glob(".*tmp*"))  # written atomically: no temporary left

    def test_odd_sizes_lose_one_pixel_for_h264(self, voxel_scene):
        camera = voxel_scene.train[0].camera.scaled(17 / 16)
        assert (camera.width, camera.height) == (17, 17)
        even = even_sized(camera)
        assert (even.width, even.height, even.cx, even.fx) == (16, 16, camera.cx, camera.fx)


class TestExposureSweep:
    @pytest.mark.parametrize("output", ["ldr", "hdr-srgb", "hdr-filmic", "hdr-mulaw"])
    def test_monotonic_in_brightness(self, voxel_mono, tmp_path, output):
        evs = np.linspace(-6, 6, 13).tolist()
        images = render_exposure_sweep(
            voxel_mono,
            voxel_mono.scene.test[0].camera,
            evs,
            tmp_path / "sweep.mp4",
            tmp_path / "strip.png",
            output=output,
        )
        brightness = [float(image.mean()) for image in images]
        assert all(b >= a for a, b in zip(brightness, brightness[1:])), brightness
        assert brightness[-1] > brightness[0] + 50
        assert len(video_frames(tmp_path / "sweep.mp4")) == 13
        strip = read_image(tmp_path / "strip.png")
        assert strip.shape == (16 + 14, 13 * 18 - 2, 3)
        np.testing.assert_allclose(strip[:16, 36:52], images[2] / 255.0, atol=1 / 255)  # the third frame, in place

    def test_camera_response_sweep_renders_each_exposure(self, voxel_crf, tmp_path):
        camera = voxel_crf.scene.test[0].camera
        images = render_exposure_sweep(voxel_crf, camera, [-1.0, 1.0], tmp_path / "s.mp4", tmp_path / "s.png")
        expected = voxel_crf.pipeline.render(camera, 0.5 * 2.0).ldr.clamp(0, 1)
        assert np.abs(images[1].astype(int) - np.round(expected.numpy() * 255).astype(int)).max() <= 1


@pytest.fixture
def checkpoint(demo_voxel_checkpoint):
    return demo_voxel_checkpoint


@pytest.fixture
def demo():
    """The demo scene the checkpoint was trained on (outside slow tests, its tiny variant)."""
    return load_scene(DataConfig(scene="demo"))


class TestRenderCommand:
    def test_path_video(self, checkpoint, demo, tmp_path):
        main(
            [
                "render",
                "--checkpoint",
                str(checkpoint),
                "--path",
                "interpolate",
                "--frames",
                "6",
                "--scale",
                "0.5",
                "--video",
                str(tmp_path / "glide.mp4"),
                "--exr-frames",
                str(tmp_path / "exr"),
                "--output",
                "hdr-srgb",
            ]
        )
        frames = video_frames(tmp_path / "glide.mp4")
        half = demo.train[0].camera.width // 2
        assert len(frames) == 6 and frames[0].shape == (half, half, 3)
        assert len(list((tmp_path / "exr").glob("*.exr"))) == 6

    def test_dataset_path_has_one_frame_per_camera(self, checkpoint, demo, tmp_path):
        main(
            ["render", "--checkpoint", str(checkpoint), "--path", "dataset", "--out", str(tmp_path), "--scale", "0.25"]
        )
        assert len(video_frames(tmp_path / "path_dataset.mp4")) == len({view.view_id for view in demo.test})

    def test_sweep(self, checkpoint, demo, tmp_path):
        main(
            [
                "render",
                "--checkpoint",
                str(checkpoint),
                "--sweep",
                "--frames",
                "5",
                "--view",
                "2",
                "--out",
                str(tmp_path),
                "--scale",
                "0.5",
            ]
        )
        half = demo.train[0].camera.width // 2
        assert len(video_frames(tmp_path / "exposure_sweep.mp4")) == 5
        assert read_image(tmp_path / "exposure_sweep.png").shape == (half + 14, 5 * (half + 2) - 2, 3)

    def test_bad_flags_are_named(self, checkpoint):
        with pytest.raises(ValueError, match="--path and --sweep"):
            main(["render", "--checkpoint", str(checkpoint), "--path", "spiral", "--sweep"])
        with pytest.raises(ValueError, match="--view 99"):
            main(["render", "--checkpoint", str(checkpoint), "--sweep", "--view", "99"])


class TestEvSheet:
    def test_photo_then_renders_at_the_views_own_exposure(self, voxel_crf):
        view = voxel_crf.scene.test[0]
        sheet = ev_sheet(voxel_crf, view, (-2.0, 0.0, 2.0))
        height, width = view.camera.height, view.camera.width
        assert sheet.shape == (height + 14, 4 * (width + 2) - 2, 3)
        np.testing.assert_array_equal(sheet[:height, :width], np.round(view.image.numpy() * 255))
        # The baseline's learned response renders any exposure: the +2 tile is the view at 4x its time.
        expected = voxel_crf.pipeline.render(view.camera, view.exposure * 4.0).ldr.clamp(0, 1).numpy()
        tile = sheet[:height, 3 * (width + 2) : 3 * (width + 2) + width].astype(int)
        assert np.abs(tile - np.round(expected * 255).astype(int)).max() <= 1

    def test_brightness_rises_with_ev(self, voxel_mono):
        view = voxel_mono.scene.test[0]
        sheet = ev_sheet(voxel_mono, view, (-4.0, -2.0, 0.0, 2.0, 4.0))
        width, height = view.camera.width, view.camera.height
        means = [float(sheet[:height, i * (width + 2) : i * (width + 2) + width].mean()) for i in range(1, 6)]
        assert all(b > a for a, b in zip(means, means[1:])), means

    def test_command_writes_one_sheet_per_test_camera_unless_told_not_to(self, checkpoint, demo, tmp_path):
        main(["render", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "a"), "--max-views", "2"])
        sheets = sorted((tmp_path / "a").glob("*_ev_sheet.png"))
        assert len(sheets) == 2
        width = demo.test[0].camera.width
        assert read_image(sheets[0]).shape[1] == 6 * (width + 2) - 2  # the photo and EV -4, -2, 0, +2, +4
        main(
            ["render", "--checkpoint", str(checkpoint), "--out", str(tmp_path / "b"), "--max-views", "1", "--sheet-evs"]
        )
        assert not list((tmp_path / "b").glob("*_ev_sheet.png"))
        with pytest.raises(ValueError, match=r"--sheet-evs applies to test-view renders \(no --path or --sweep\) only"):
            main(["render", "--checkpoint", str(checkpoint), "--sweep", "--sheet-evs", "1"])
