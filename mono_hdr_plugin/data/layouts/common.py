"""Helpers shared by the layout readers and writers.

Every value a reader takes from a dataset file goes through one of the `json_*` checks (or
`check_exposure`, `check_finite`), so a value of the wrong type, NaN, Inf, out of range or not
usable as a file name is a DatasetError naming the file and the key, never a traceback.
"""

import contextlib
import json
import math
import os
import re
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from mono_hdr_plugin.core.camera_optimizer import EXACT, STRUCTURE_FROM_MOTION
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.validation import ANY_FINITE, Rule, numeric
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import check_readable, write_json

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
UNKNOWN_EXPOSURE = 1.0
"""Seconds given to a photo whose exposure is unknown (null in exposures.json, or a layout without
exposures); the reader names it in the scene's metadata["unknown_exposures"] for the trainer to learn."""
MAX_NAME_BYTES = 255
"""Longest file or folder name common file systems allow."""
POSE_SOURCE_FILE = "pose_source.json"
"""Written beside a layout's poses when they are exact (`mono-hdr synth`); without it, the poses of a
COLMAP or LLFF folder are taken to come from structure from motion."""


def natural_key(name: str) -> list:
    """Sort key that orders numbers by value: view 2 before view 10 (never string order)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def load_json(path: Path, fix: str):
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder, not a JSON file; remove or rename it")
    if not path.is_file():
        raise missing(path, fix)
    check_readable(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError) as error:  # bad JSON, bad UTF-8, integers too long to read, deep nesting
        reason = str(error).splitlines()[0][:160] if str(error) else type(error).__name__
        raise DatasetError(f"{path}: not valid JSON ({reason}); repair or regenerate it") from error


def shown(value) -> str:
    """A value from a file as it appears in an error message (shortened)."""
    text = repr(value.item() if isinstance(value, np.generic) else value)
    return text if len(text) <= 60 else text[:57] + "..."


def json_object(value, where: str) -> dict:
    if not isinstance(value, dict):
        raise DatasetError(f"{where} must be a JSON object {{...}}, got {shown(value)}")
    return value


def json_number(value, where: str, rule: Rule = ANY_FINITE) -> float:
    """A finite number within `rule`, from a JSON value (booleans and strings are not numbers)."""
    if not numeric(value):
        raise DatasetError(f"{where} must be {rule.describe(False)}, got {shown(value)}")
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float range
        number = math.inf
    if not math.isfinite(number):
        raise DatasetError(f"{where} must be {rule.describe(False)}, got {shown(value)} (NaN or Inf)")
    if not rule.accepts(number):
        raise DatasetError(f"{where} must be {rule.describe(False)}, got {shown(value)}")
    return number


def json_name(value, where: str) -> str:
    """A non-empty string that can be part of a file name here (no NUL, encodable)."""
    if not isinstance(value, str) or not value.strip():
        raise DatasetError(f"{where} must be a non-empty file name, got {shown(value)}")
    try:
        os.fsencode(value)
    except UnicodeEncodeError:
        raise DatasetError(f"{where} {shown(value)} is not a valid file name (broken unicode)") from None
    if "\0" in value:
        raise DatasetError(f"{where} {shown(value)} is not a valid file name (NUL character)")
    if any(len(os.fsencode(part)) > MAX_NAME_BYTES for part in value.split("/")):
        raise DatasetError(f"{where} {shown(value)} is not a valid file name (a part is over {MAX_NAME_BYTES} bytes)")
    return value


def json_matrix(value, where: str, rows: int, columns: int) -> np.ndarray:
    """A rows x columns list of lists of finite numbers."""
    if not (
        isinstance(value, list)
        and len(value) == rows
        and all(isinstance(row, list) and len(row) == columns for row in value)
    ):
        raise DatasetError(f"{where} must be a {rows}x{columns} list of rows of numbers, got {shown(value)}")
    return np.array(
        [[json_number(item, f"{where}[{i}][{j}]") for j, item in enumerate(row)] for i, row in enumerate(value)],
        dtype=np.float64,
    )


def check_exposure(value, where: str) -> float:
    """A positive, finite exposure time in seconds, or an error naming where it came from."""
    exposure = math.nan
    if not isinstance(value, bool):
        with contextlib.suppress(TypeError, ValueError, OverflowError):  # not a number: named below
            exposure = float(value)
    if not (math.isfinite(exposure) and exposure > 0):
        raise DatasetError(
            f"{where}: exposure time {shown(value)} is not a positive number of seconds; fix the exposure value"
        )
    return exposure


def point_colours_u8(count: int, colours: torch.Tensor | None) -> np.ndarray:
    """[count, 3] uint8 colours of a scene's points for a writer (grey where it has none, as 3DGS)."""
    if colours is None:
        return np.full((count, 3), 128, np.uint8)
    return (colours.clamp(0, 1).numpy() * 255).round().astype(np.uint8)


def camera_from(where: str, **fields) -> Camera:
    """A Camera; a bad pose, focal length or near/far is reported naming the file it came from."""
    try:
        return Camera(**fields)
    except ValueError as error:
        raise DatasetError(f"{where}: {error}") from error


def check_finite(array: np.ndarray, path: Path, what: str) -> np.ndarray:
    try:
        array = np.asarray(array, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise DatasetError(f"{path}: {what} is not numeric ({error}); regenerate the file") from error
    if not np.isfinite(array).all():
        raise DatasetError(f"{path}: {what} contains NaN or Inf; re-run the pose estimation or fix the file")
    return array


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from an image header, without decoding the pixels."""
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder, not an image file; check the dataset's file names")
    if not path.is_file():
        raise missing(path, "check that every image the dataset lists is present")
    check_readable(path)
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, UnidentifiedImageError) as error:
        raise DatasetError(f"{path}: not a readable image ({error}); export it again") from error


def check_one_size(sizes: dict[Path, tuple[int, int]], folder: Path) -> tuple[int, int]:
    """The one (width, height) all images share, or an error naming two that differ."""
    distinct: dict[tuple[int, int], Path] = {}
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
    match = re.fullmatch(r"(.+)_([0-9]{1,9})\.[A-Za-z]+", name)
    return (match.group(1), int(match.group(2))) if match else None


def read_pose_source(folder: Path) -> str:
    """Where a COLMAP or LLFF folder's poses come from (scene.metadata["poses"], which decides
    `--camera-opt auto`): exact where the studio wrote them (POSE_SOURCE_FILE), else structure from motion."""
    path = folder / POSE_SOURCE_FILE
    if not path.is_file():
        return STRUCTURE_FROM_MOTION
    poses = json_object(load_json(path, f'write {{"poses": "{EXACT}"}} or delete it'), str(path)).get("poses")
    if poses not in (EXACT, STRUCTURE_FROM_MOTION):
        raise DatasetError(f'{path}: "poses" must be "{EXACT}" or "{STRUCTURE_FROM_MOTION}", got {shown(poses)}')
    return poses


def write_pose_source(metadata: dict, folder: Path) -> None:
    """Mark a written COLMAP or LLFF folder's poses as exact when the scene's are (the studio's), so
    reading it back does not refine them."""
    if metadata.get("poses") == EXACT:
        write_json(folder / POSE_SOURCE_FILE, {"poses": EXACT})
