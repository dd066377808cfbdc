"""Stage 1: the photos to use (a folder, or frames of a video), read upright, copied for structure
from motion, and checked to come from one camera at one size."""

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError
from rich.console import Console
from rich.progress import track

from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig
from mono_hdr_plugin.apps.process_data.records import VideoRecord
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import write_png
from mono_hdr_plugin.data.layouts.common import natural_key
from mono_hdr_plugin.data.photos.exif import PhotoExif, read_exif
from mono_hdr_plugin.data.photos.raw import RAW_SUFFIXES, RawResponse, encode, is_raw, read_raw
from mono_hdr_plugin.data.photos.video import extract_frames

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
MIN_IMAGES = 3
"""Structure from motion places no fewer photos than this."""


def find_inputs(
    config: ProcessDataConfig, frames: Path, console: Console
) -> tuple[list[Path], list[str], VideoRecord | None]:
    """The photos of --images, or the frames of --video extracted into `frames`; the ignored files; the video."""
    if config.video is None:
        assert config.images is not None  # check_config requires one of --images and --video
        return (*find_photos(config.images), None)
    kept, dropped = extract_frames(
        config.video, frames, config.fps, min_sharpness=config.min_sharpness, console=console
    )
    video = VideoRecord(
        source=str(config.video),
        fps=config.fps,
        candidates=len(kept) + len(dropped),
        kept=len(kept),
        dropped_times=[round(frame.time, 3) for frame in dropped],
    )
    return (*find_photos(frames), video)


def find_photos(folder: Path) -> tuple[list[Path], list[str]]:
    """The photos in `folder` in natural file-name order (IMG_2 before IMG_10), and the ignored files.

    A JPEG/PNG/TIFF with the same name as a RAW file is the camera's rendering of that RAW: the
    RAW is used and the twin ignored.
    """
    if not folder.is_dir():
        raise missing(folder, "pass --images a folder of JPEG, PNG, TIFF or RAW photos")
    suffixes = PHOTO_SUFFIXES + RAW_SUFFIXES
    found = sorted(
        (
            path
            for path in folder.iterdir()
            if path.is_file() and path.suffix.lower() in suffixes and not path.name.startswith(".")
        ),
        key=lambda path: natural_key(path.name),
    )
    raw_stems = {path.stem for path in found if is_raw(path)}
    photos = [path for path in found if is_raw(path) or path.stem not in raw_stems]
    ignored = [path.name for path in found if path not in photos]
    if not photos:
        raise DatasetError(
            f"{folder}: no photos found (looked for {', '.join(suffixes)}); "
            "point --images at the folder that holds the pictures"
        )
    if len(photos) < MIN_IMAGES:
        raise DatasetError(
            f"{folder}: only {len(photos)} photo(s); structure from motion needs at least "
            f"{MIN_IMAGES} overlapping photos, 20-100 around the scene work best"
        )
    return photos, ignored


def load_photo(path: Path) -> tuple[np.ndarray, PhotoExif]:
    """Pixels as float32 [H, W, 3] in [0, 1], turned upright by the EXIF orientation, and the EXIF.

    RAW files give linear pixels (photos.raw); every other format gives its stored code values.
    """
    if is_raw(path):
        return read_raw(path)
    try:
        with Image.open(path) as image:
            image.load()  # decode now: a truncated file fails here with its name
            exif = read_exif(image)
            upright = ImageOps.exif_transpose(image)
            if upright.mode in ("I;16", "I;16B", "I;16L", "I"):
                pixels = np.asarray(upright, np.float32) / 65535.0
                pixels = np.repeat(pixels[..., None], 3, axis=-1)
            else:
                pixels = np.asarray(upright.convert("RGB"), np.float32) / 255.0
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as error:
        raise DatasetError(
            f"{path}: cannot read the photo ({error}); export it again or move it out of the folder"
        ) from error
    return pixels, exif


@dataclass
class StagedPhoto:
    """A readable photo, copied for structure from motion; its pixels are read again when needed."""

    source: Path
    name: str
    exif: PhotoExif
    raw: bool
    brightness: float
    """Mean code value of the photo."""
    linear: Path | None = None
    """RAW only: its linear pixels, saved once (LibRaw's demosaicing is slow)."""


def photo_pixels(photo: StagedPhoto, raw_response: RawResponse) -> tuple[np.ndarray, np.ndarray | None]:
    """(LDR code values, linear pixels or None): a RAW photo is both; any other photo only the first."""
    if photo.raw:
        assert photo.linear is not None  # stage_photos saves the linear pixels of every RAW photo
        linear = np.load(photo.linear)
        return encode(linear, raw_response), linear
    return load_photo(photo.source)[0], None


def stage_photos(
    sources: list[Path], work: Path, raw_response: RawResponse, console: Console
) -> tuple[list[StagedPhoto], list[tuple[int, int]]]:
    """8-bit upright copies `work/input/<index:03d>_0.png` (the HDR-GS naming) for structure from
    motion; each one's (width, height) after EXIF orientation.

    RAW photos are demosaiced once: their linear pixels are kept in work/linear, their SfM copy
    goes through the RAW response.
    """
    staged, sizes, unreadable = [], [], []
    for index, path in enumerate(track(sources, description="reading photos", console=console)):
        try:
            pixels, exif = load_photo(path)
        except DatasetError as error:
            unreadable.append(str(error))
            continue
        stage = StagedPhoto(source=path, name=f"{index:03d}_0.png", exif=exif, raw=is_raw(path), brightness=0.0)
        if stage.raw:
            stage.linear = work / "linear" / f"{index:03d}.npy"
            stage.linear.parent.mkdir(exist_ok=True)
            np.save(stage.linear, pixels)
            pixels = encode(pixels, raw_response)
        stage.brightness = float(pixels.mean())
        write_png(work / "input" / stage.name, pixels)
        staged.append(stage)
        sizes.append((pixels.shape[1], pixels.shape[0]))
    if unreadable:
        raise DatasetError(
            f"{len(unreadable)} photo(s) cannot be read; fix or remove them:\n  " + "\n  ".join(unreadable)
        )
    check_one_camera([s.source.name for s in staged], sizes, [s.exif for s in staged], sources[0].parent)
    return staged, sizes


def check_one_camera(sources: list[str], sizes: list[tuple[int, int]], exifs: list[PhotoExif], folder: Path) -> None:
    """All photos must come from one camera at one size, held upright or sideways: one set of
    intrinsics is estimated per orientation."""
    by_size = Counter(sizes)
    upright = {(min(w, h), max(w, h)) for w, h in by_size}
    if len(upright) > 1:
        listing = ", ".join(
            f"{count} at {w}x{h} (e.g. {sources[sizes.index((w, h))]})" for (w, h), count in by_size.most_common()
        )
        raise DatasetError(
            f"{folder}: photos of different sizes after EXIF orientation ({listing}); "
            "process one camera at a time (move the others to another folder) or resize them to one "
            "size (portrait and landscape photos of one size are fine)"
        )
    cameras = Counter(exif.camera for exif in exifs if exif.camera)
    if len(cameras) > 1:
        listing = ", ".join(f"{count} from {name!r}" for name, count in cameras.most_common())
        raise DatasetError(
            f"{folder}: photos from several cameras ({listing}); one set of intrinsics is "
            "estimated per dataset: process each camera's photos in its own folder"
        )
