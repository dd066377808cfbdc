"""RAW photos through rawpy (LibRaw): linear demosaiced pixels and the exposure in their metadata.

LibRaw subtracts the black level, scales the white level to 1, applies the camera's as-shot
white balance, demosaics (AHD) and converts to linear sRGB primaries. With gamma (1, 1), no
automatic brightening and no "maximum adjustment" (by default LibRaw takes a bright photo's own
maximum as its white level, which scales each photo differently) the values stay proportional
to the light the sensor collected, the same scale in every photo, which is
what a bracket merge and an exposure model need. An LDR view of a RAW photo is that linear
image through a chosen response curve (`encode`), clipped at white.
"""

from datetime import datetime
from pathlib import Path

import numpy as np

from mono_hdr_plugin.core.colour import ResponseCurve, decode_curve, encode_curve
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.photos.exif import PhotoExif

RAW_SUFFIXES = (
    ".dng",
    ".cr2",
    ".cr3",
    ".crw",
    ".nef",
    ".nrw",
    ".arw",
    ".srf",
    ".sr2",
    ".raf",
    ".orf",
    ".rw2",
    ".pef",
    ".srw",
    ".3fr",
    ".iiq",
    ".rwl",
    ".x3f",
)
RawResponse = ResponseCurve
"""The standard response curves a RAW photo's LDR view can be encoded with."""


def is_raw(path: Path) -> bool:
    return path.suffix.lower() in RAW_SUFFIXES


def read_raw(path: Path) -> tuple[np.ndarray, PhotoExif]:
    """Linear pixels float32 [H, W, 3] (1 = sensor white, upright by the file's orientation) and metadata."""
    import rawpy

    try:
        with open(path, "rb") as file, rawpy.imread(file) as raw:  # a file: LibRaw takes UTF-8 paths only
            pixels = raw.postprocess(
                gamma=(1, 1),
                no_auto_bright=True,
                output_bps=16,
                use_camera_wb=True,
                output_color=rawpy.ColorSpace.sRGB,
                adjust_maximum_thr=0.0,
            )
            other = raw.other
    except (rawpy.LibRawError, rawpy.NotSupportedError, OSError, ValueError) as error:
        raise DatasetError(
            f"{path}: LibRaw cannot read this RAW file ({type(error).__name__}: {error}); export it "
            "again from the camera, convert it to DNG, or move it out of the folder"
        ) from error
    return pixels.astype(np.float32) / 65535.0, raw_metadata(other)


def raw_metadata(other) -> PhotoExif:
    """rawpy's `other` (shutter, aperture, ISO, time) as PhotoExif; LibRaw reports unknown values as 0."""

    def positive(value) -> float | None:
        value = float(value)
        return value if np.isfinite(value) and value > 0 else None

    known_time = isinstance(other.timestamp, datetime) and other.timestamp.year > 1970  # 0 means none
    return PhotoExif(
        exposure_time=positive(other.shutter_speed),
        f_number=positive(other.aperture),
        iso=positive(other.iso_speed),
        timestamp=other.timestamp.timestamp() if known_time else None,
    )


def encode(linear: np.ndarray, response: RawResponse) -> np.ndarray:
    """Linear pixels through a standard response curve, clipped to [0, 1]: the LDR photo of a RAW file."""
    return np.clip(encode_curve(np.clip(linear, 0.0, 1.0), response), 0.0, 1.0).astype(np.float32)


def decode(encoded: np.ndarray, response: RawResponse) -> np.ndarray:
    """Inverse of `encode` on [0, 1]."""
    return decode_curve(np.clip(encoded, 0.0, 1.0), response).astype(np.float32)
