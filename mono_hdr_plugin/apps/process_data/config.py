"""The flags of `mono-hdr process-data` and the checks they pass before any photo is read."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar, Literal

from mono_hdr_plugin.core.validation import POSITIVE, FlagError, at_least, between, check_flags
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.layouts.hdr_gs import REPORT_FILE
from mono_hdr_plugin.data.outputs import check_replaceable
from mono_hdr_plugin.data.photos.brackets import BracketTolerances
from mono_hdr_plugin.data.photos.raw import RawResponse

DOWNSCALES = (1, 2, 4)


@dataclass
class ProcessDataConfig:
    """Turn photos or a video into a dataset: poses by structure from motion, exposures from EXIF,
    HDR views merged from exposure brackets."""

    out: Path
    """Dataset folder to create (HDR-GS layout); train with `mono-hdr train gs --data OUT`."""
    images: Path | None = None
    """Folder of photos (JPEG, PNG, TIFF or camera RAW) of one scene, all from one camera."""
    video: Path | None = None
    """A video of the scene, instead of --images: frames are taken at --fps, the blurriest dropped."""
    fps: float = 2.0
    """Video: frames per second of clip to keep (each the sharpest of three candidates around its time)."""
    min_sharpness: float = 0.5
    """Video: drop a frame less sharp than this fraction of the median kept frame."""
    exposure: float | None = None
    """Exposure time in seconds for photos whose EXIF has none (and no --exposure-csv row)."""
    exposure_csv: Path | None = None
    """CSV of `file name,seconds` rows for photos whose EXIF has no exposure time."""
    brackets: bool = True
    """Find bracket sets among the photos (one viewpoint, several exposures) and merge each into an
    HDR view; --no-brackets keeps every photo as its own LDR view."""
    bracket: BracketTolerances = field(default_factory=BracketTolerances)
    """How close two photos must be, in time and pose, to count as one viewpoint."""
    raw_response: RawResponse = "srgb"
    """Response curve that turns a RAW photo's linear pixels into its LDR view."""
    test_every: int = 8
    """Hold out every N-th single-exposure view for testing (bracketed views always train)."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Which photo pairs to match: exhaustive (every pair, small sets), sequential (neighbours in
    file-name order: videos, large sets), or auto (exhaustive up to 80 photos)."""
    mapper: Literal["auto", "incremental", "incremental-forward", "global"] = "auto"
    """How structure from motion places the photos: COLMAP's incremental mapper (incremental), the
    same started from a pair with little parallax, as walking or driving straight ahead gives
    (incremental-forward), GLOMAP's global mapper (global), or auto: each in that order until one
    places every photo, keeping the model that places the most."""
    downscale: Literal[1, 2, 4] = 1
    """Shrink the training images by this factor (area averaging); intrinsics are scaled to match."""
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE"] = "SIMPLE_RADIAL"
    """COLMAP camera model. Models with lens distortion are estimated, then the images undistorted;
    SIMPLE_PINHOLE/PINHOLE assume distortion-free images (renders, already undistorted photos)."""
    min_registered: float = 0.5
    """Fail when structure from motion places fewer than this fraction of the photos."""
    sequential_overlap: int = 10
    """Sequential matcher: match each photo with this many following photos."""
    overwrite: bool = False
    """Replace --out when it exists already."""
    seed: int = 0
    """Random seed of structure from motion (same photos, same seed: same result)."""
    num_threads: int = -1
    """CPU threads for structure from motion (-1: all)."""

    # Every N-th view is held out, so N >= 2; the others are fractions of frames or photos.
    flag_rules: ClassVar = {
        "fps": POSITIVE,
        "min_sharpness": between(0, 1, high_open=True),
        "exposure": POSITIVE,
        "test_every": at_least(2),
        "min_registered": between(0, 1, low_open=True),
    }


def check_config(config: ProcessDataConfig) -> None:
    """Flag values that cannot work, before any photo is read: the flag rules, then what they cannot
    say (one input of two, a choice of sizes), then the output folder."""
    if (config.images is None) == (config.video is None):
        raise FlagError("pass either --images FOLDER (photos) or --video FILE, not both or neither")
    check_flags(config)
    # A Literal the command line enforces; a config built in Python is checked here.
    if config.downscale not in DOWNSCALES:
        raise FlagError(f"--downscale must be 1, 2 or 4, got {config.downscale}")
    check_output(config)


def check_output(config: ProcessDataConfig) -> None:
    """--out must be a folder to create (or one process-data wrote, with --overwrite), apart from the inputs."""
    if config.out.exists() and not config.out.is_dir():
        raise DatasetError(f"{config.out}: is a file; --out must be a folder to create")
    if config.out.exists() and any(config.out.iterdir()) and not config.overwrite:
        raise DatasetError(
            f"{config.out}: already exists and is not empty; pass --overwrite to replace it or choose another --out"
        )
    if config.images is not None and config.out.resolve() == config.images.resolve():
        raise FlagError("--out must differ from --images: the photos would be replaced")
    # --out is replaced as a whole: only a dataset process-data wrote, never one holding the inputs.
    check_replaceable(
        config.out, config.out / REPORT_FILE, [config.images, config.exposure_csv], "process-data --overwrite replaces"
    )
