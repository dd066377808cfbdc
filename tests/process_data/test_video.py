"""Video input: frames at a chosen rate, the blurriest dropped; bad videos; process-data --video."""

from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from process_data_photos import textured_scene

from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data
from mono_hdr_plugin.apps.studio.capture import capture
from mono_hdr_plugin.apps.studio.render import render_scene
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_image
from mono_hdr_plugin.data.photos.video import extract_frames, sharpness


def write_video(path: Path, frames: list[np.ndarray], fps: float) -> Path:
    """float [H, W, 3] frames in [0, 1] -> an H.264 MP4 (what phones record)."""
    height, width = frames[0].shape[:2]
    writer = imageio_ffmpeg.write_frames(
        str(path), (width, height), fps=fps, macro_block_size=1, quality=9, ffmpeg_log_level="error"
    )
    writer.send(None)
    for frame in frames:
        writer.send(np.ascontiguousarray((np.clip(frame, 0, 1) * 255).round().astype(np.uint8)))
    writer.close()
    return path


def blur(image: np.ndarray, radius: int = 3) -> np.ndarray:
    """Box blur: what a shaken hand does to a frame."""
    padded = np.pad(image, ((radius, radius), (radius, radius), (0, 0)), mode="edge")
    size = 2 * radius + 1
    return (
        sum(padded[dy : dy + image.shape[0], dx : dx + image.shape[1]] for dy in range(size) for dx in range(size))
        / size**2
    )


@pytest.fixture(scope="module")
def noise_frames():
    rng = np.random.default_rng(0)
    return [np.kron(rng.random((12, 16, 3)), np.ones((4, 4, 1))) for _ in range(18)]


class TestSharpness:
    def test_blur_lowers_it(self, noise_frames):
        assert sharpness(blur(noise_frames[0])) < 0.2 * sharpness(noise_frames[0])

    def test_flat_image_has_none(self):
        assert sharpness(np.full((8, 8, 3), 0.5)) == 0.0


class TestExtractFrames:
    def test_keeps_the_sharpest_of_each_run_and_drops_a_blurred_run(self, noise_frames, tmp_path):
        # 6 frames per second; candidates come at 2 fps x 3 = 6 per second, in runs of three.
        # In each run one frame is sharp, except the fourth run, blurred through.
        frames = [
            frame if index % 3 == 1 and index // 3 != 3 else blur(frame) for index, frame in enumerate(noise_frames)
        ]
        video = write_video(tmp_path / "clip.mp4", frames, fps=6)
        kept, dropped = extract_frames(video, tmp_path / "frames", fps=2.0)
        assert len(kept) + len(dropped) == 18
        assert [round(frame.time * 6) for frame in kept] == [1, 4, 7, 13, 16]
        assert sorted(path.name for path in (tmp_path / "frames").iterdir()) == [frame.path.name for frame in kept]
        assert min(frame.sharpness for frame in kept) > 3 * max(frame.sharpness for frame in dropped)
        assert read_image(kept[0].path).shape == (48, 64, 3)

    def test_no_threshold_keeps_one_per_run(self, noise_frames, tmp_path):
        video = write_video(tmp_path / "clip.mp4", [blur(frame) for frame in noise_frames], fps=6)
        kept, _ = extract_frames(video, tmp_path / "frames", fps=2.0, min_sharpness=0.0)
        assert len(kept) == 6

    def test_video_with_no_frames_names_the_file(self, tmp_path):
        writer = imageio_ffmpeg.write_frames(
            str(tmp_path / "empty.mp4"), (64, 48), fps=6, macro_block_size=1, ffmpeg_log_level="quiet"
        )
        writer.send(None)
        writer.close()
        with pytest.raises(DatasetError, match="empty.mp4: ffmpeg finds no video frames"):
            extract_frames(tmp_path / "empty.mp4", tmp_path / "frames", fps=2.0)

    def test_not_a_video_names_the_file(self, tmp_path):
        (tmp_path / "notes.mp4").write_text("these are not frames")
        with pytest.raises(DatasetError, match="notes.mp4: ffmpeg finds no video frames"):
            extract_frames(tmp_path / "notes.mp4", tmp_path / "frames", fps=2.0)

    def test_missing_video(self, tmp_path):
        with pytest.raises(DatasetError, match="gone.mp4: file not found.*--video"):
            extract_frames(tmp_path / "gone.mp4", tmp_path / "frames", fps=2.0)

    def test_bad_rate(self, noise_frames, tmp_path):
        video = write_video(tmp_path / "clip.mp4", noise_frames[:3], fps=6)
        with pytest.raises(DatasetError, match="--fps must be a positive"):
            extract_frames(video, tmp_path / "frames", fps=0.0)


class TestVideoFlags:
    def test_images_and_video_together(self, tmp_path):
        with pytest.raises(FlagError, match="either --images FOLDER.*or --video FILE"):
            process_data(ProcessDataConfig(images=tmp_path, video=tmp_path / "a.mp4", out=tmp_path / "out"))

    def test_neither(self, tmp_path):
        with pytest.raises(FlagError, match="either --images FOLDER"):
            process_data(ProcessDataConfig(out=tmp_path / "out"))


@pytest.mark.slow
class TestProcessVideo:
    def test_walkaround_clip_to_dataset(self, studio_cache, texture, tmp_path):
        """A 24-view arc of the textured scene filmed at 6 fps, every third frame shaken."""
        scene = textured_scene(texture, views=24, resolution=192)
        radiance = render_scene(scene).radiance
        frames = [capture(view, 1.5, scene.effects, scene.capture) for view in radiance]
        frames = [frame if index % 3 == 0 else blur(frame, 2) for index, frame in enumerate(frames)]
        video = write_video(tmp_path / "walk.mp4", frames, fps=6)
        report = process_data(
            ProcessDataConfig(video=video, out=tmp_path / "data", fps=2.0, camera_model="SIMPLE_PINHOLE", num_threads=2)
        )
        assert report.video.kept == 8 and report.video.candidates == 24
        assert len(report.registered) == 8 and report.hdr_views == []
        assert not report.exposures_known and report.exposure_range is None
