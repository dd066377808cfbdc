"""Frames from a video for process-data: sampled at a chosen rate, the blurriest ones dropped.

ffmpeg (the binary that imageio-ffmpeg ships) decodes the clip at `oversample` times the
requested rate; of each run of `oversample` consecutive candidates the sharpest is kept, so the
kept frames still come at the requested rate but each is the least shaken one near its time.
Kept frames far less sharp than the others (motion blur during a fast pan) are dropped too:
structure from motion cannot place them and they would blur the model.

Sharpness is the variance of the Laplacian of the luminance (Pech-Pacheco et al. 2000).
"""

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console

from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import write_png

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass
class Frame:
    """One candidate frame: its time in the clip, its sharpness, and its file when kept."""

    time: float
    sharpness: float
    path: Path | None = None


def sharpness(image: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the luminance of [H, W, 3] pixels in [0, 1]."""
    luma = image.astype(np.float32) @ LUMA
    laplacian = luma[:-2, 1:-1] + luma[2:, 1:-1] + luma[1:-1, :-2] + luma[1:-1, 2:] - 4 * luma[1:-1, 1:-1]
    return float(laplacian.var())


def _first_line(error: Exception) -> str:
    return next((line for line in str(error).splitlines() if line.strip()), type(error).__name__)


def _open_frames(video: Path, fps: float, oversample: int) -> tuple[Iterator[bytes], int, int]:
    """ffmpeg's frame reader decoding `video` at `fps * oversample`, and the frames' width and height."""
    import imageio_ffmpeg

    if not video.is_file():
        raise missing(video, "pass --video a video file (MP4, MOV, ...)")
    if not fps > 0 or oversample < 1:
        raise DatasetError(f"--fps must be a positive number of frames per second, got {fps}")
    try:
        reader = imageio_ffmpeg.read_frames(str(video), output_params=["-vf", f"fps={fps * oversample:g}"])
        meta = next(reader)
    except (OSError, RuntimeError, StopIteration) as error:
        raise DatasetError(
            f"{video}: ffmpeg finds no video frames in it ({_first_line(error)}); check that "
            "the file is a complete video (MP4, MOV, ...) that plays elsewhere"
        ) from error
    width, height = meta["size"]
    return reader, width, height


def _write_sharpest(
    reader: Iterator[bytes], video: Path, folder: Path, size: tuple[int, int], rate: float, oversample: int
) -> tuple[list[Frame], list[Frame]]:
    """Every candidate frame, and the sharpest of each run of `oversample` (those written to `folder`)."""
    height, width = size
    candidates: list[Frame] = []
    best: list[Frame] = []
    try:
        for index, data in enumerate(reader):
            pixels = np.frombuffer(data, np.uint8).reshape(height, width, 3)
            frame = Frame(time=index / rate, sharpness=sharpness(pixels / np.float32(255)))
            candidates.append(frame)
            if index % oversample == 0:
                best.append(frame)
            elif frame.sharpness > best[-1].sharpness:
                best[-1].path = None
                best[-1] = frame
            else:
                continue
            frame.path = folder / f"frame_{len(best):05d}.png"  # replaces a less sharp one of its run
            write_png(frame.path, pixels / np.float32(255))
    except (OSError, RuntimeError) as error:
        raise DatasetError(
            f"{video}: ffmpeg stopped after {len(candidates)} frame(s) ({_first_line(error)}); "
            "the file may be truncated: export it again"
        ) from error
    return candidates, best


def _drop_blurred(best: list[Frame], min_sharpness: float) -> None:
    """Delete the written frames below `min_sharpness` times the median sharpness of `best`."""
    threshold = min_sharpness * float(np.median([frame.sharpness for frame in best]))
    for frame in best:
        if frame.sharpness < threshold:
            assert frame.path is not None  # every frame in `best` was written
            frame.path.unlink()
            frame.path = None


def extract_frames(
    video: Path,
    folder: Path,
    fps: float,
    oversample: int = 3,
    min_sharpness: float = 0.5,
    console: Console | None = None,
) -> tuple[list[Frame], list[Frame]]:
    """Write the kept frames to `folder` as frame_00001.png ...; returns (kept, dropped) candidates.

    fps: frames per second of clip to keep; min_sharpness: a kept frame below this fraction of the
    median sharpness of the kept frames is dropped.
    """
    reader, width, height = _open_frames(video, fps, oversample)
    console = console or Console(quiet=True)
    folder.mkdir(parents=True, exist_ok=True)
    with console.status(f"reading frames of {video.name}"):
        candidates, best = _write_sharpest(reader, video, folder, (height, width), fps * oversample, oversample)
    if not candidates:
        raise DatasetError(f"{video}: the video has no frames that ffmpeg can decode; record or export it again")
    _drop_blurred(best, min_sharpness)
    kept = [frame for frame in best if frame.path is not None]
    return kept, [frame for frame in candidates if frame.path is None]
