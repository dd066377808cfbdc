"""Helpers shared by the layout readers and writers."""

import json
import math
import re
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from mono_hdr_plugin.cameras import Camera
from mono_hdr_plugin.data.errors import DatasetError, missing

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def natural_key(name: str) -> list:
    """Sort key that orders numbers by value: view 2 before view 10 (never string order)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def load_json(path: Path, fix: str):
    if not path.is_file():
        raise missing(path, fix)
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise DatasetError(f"{path}: not valid JSON ({error}); repair or regenerate it") from error


def check_exposure(value, where: str) -> float:
    """A positive, finite exposure time in seconds, or an error naming where it came from."""
    try:
        exposure = float(value)
    except (TypeError, ValueError):
        exposure = math.nan
    if not (math.isfinite(exposure) and exposure > 0):
        raise DatasetError(f"{where}: exposure time {value!r} is not a positive number of seconds; "
                           "fix the exposure value")
    return exposure


def camera_from(where: str, **fields) -> Camera:
    """A Camera; a bad pose, focal length or near/far is reported naming the file it came from."""
    try:
        return Camera(**fields)
    except ValueError as error:
        raise DatasetError(f"{where}: {error}") from error


def check_finite(array: np.ndarray, path: Path, what: str) -> np.ndarray:
    array = np.asarray(array, dtype=np.float64)
    if not np.isfinite(array).all():
        raise DatasetError(f"{path}: {what} contains NaN or Inf; re-run the pose estimation or fix the file")
    return array


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from an image header, without decoding the pixels."""
    if not path.is_file():
        raise missing(path, "check that every image the dataset lists is present")
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError) as error:
        raise DatasetError(f"{path}: not a readable image ({error}); export it again") from error


def check_one_size(sizes: dict[Path, tuple[int, int]], folder: Path) -> tuple[int, int]:
    """The one (width, height) all images share, or an error naming two that differ."""
    distinct = {}
    for path, size in sizes.items():
        distinct.setdefault(size, path)
    if len(distinct) > 1:
        listing = ", ".join(f"{path.name} is {w}x{h}" for (w, h), path in distinct.items())
        raise DatasetError(f"{folder}: images of mixed sizes ({listing}); resize them all to one size")
    if not distinct:
        raise DatasetError(f"{folder}: no images found; check the dataset folder")
    return next(iter(distinct))


def split_view_exposure(name: str) -> tuple[str, int] | None:
    """`<view>_<e>.<ext>` -> (view, e), or None for any other file name."""
    match = re.fullmatch(r"(.+)_(\d+)\.[A-Za-z]+", name)
    return (match.group(1), int(match.group(2))) if match else None
