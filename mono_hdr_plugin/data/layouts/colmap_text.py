"""Checks of a COLMAP text model (cameras.txt, images.txt, points3D.txt) before pycolmap reads it.

pycolmap reports a malformed line as a C++ check that failed ("Check failed: line_stream >> ...")
and accepts some values it cannot use (a negative image width wraps around). Checked here first,
every field is named with its file and line: `images.txt line 7: QW must be a finite number, got 'abc'`.
Only syntax and ranges are checked; references between the files are left to pycolmap.
"""

import math
import re
from pathlib import Path

from mono_hdr_plugin.data.errors import DatasetError

# Parameters per camera model (COLMAP's src/colmap/sensor/models.h); the focal lengths come first.
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": (3, 1),
    "PINHOLE": (4, 2),
    "SIMPLE_RADIAL": (4, 1),
    "RADIAL": (5, 1),
    "OPENCV": (8, 2),
    "OPENCV_FISHEYE": (8, 2),
    "FULL_OPENCV": (12, 2),
    "FOV": (5, 2),
    "SIMPLE_RADIAL_FISHEYE": (4, 1),
    "RADIAL_FISHEYE": (5, 1),
    "THIN_PRISM_FISHEYE": (12, 2),
    "RAD_TAN_THIN_PRISM_FISHEYE": (16, 2),
}
MAX_ID = 2**32 - 1
INTEGER = re.compile(r"[+-]?[0-9]{1,20}")


class _Line:
    """One data line of a model file, read field by field with errors naming file, line and field."""

    def __init__(self, path: Path, number: int, text: str):
        self.path, self.line_number, self.tokens, self.position = path, number, text.split(), 0

    def fail(self, message: str) -> DatasetError:
        return DatasetError(f"{self.path} line {self.line_number}: {message}; fix the line or re-run COLMAP")

    def _next(self, field: str) -> str:
        if self.position >= len(self.tokens):
            raise self.fail(f"{field} is missing")
        self.position += 1
        return self.tokens[self.position - 1]

    def integer(self, field: str, low: int = 0, high: int = MAX_ID) -> int:
        token = self._next(field)
        if not INTEGER.fullmatch(token) or not low <= int(token) <= high:
            raise self.fail(f"{field} must be an integer from {low} to {high}, got {token!r}")
        return int(token)

    def number(self, field: str, positive: bool = False) -> float:
        token = self._next(field)
        try:
            value = float(token)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or (positive and value <= 0):
            raise self.fail(f"{field} must be a {'positive' if positive else 'finite'} number, got {token!r}")
        return value

    def word(self, field: str) -> str:
        return self._next(field)

    def remaining(self) -> int:
        return len(self.tokens) - self.position


def _data_lines(path: Path, pairs: bool = False):
    """(line number, text) of the data lines; for images.txt (`pairs`), every image line is followed by
    its observation line, which may be empty (COLMAP skips blank and comment lines only before an image)."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as error:
        raise DatasetError(
            f"{path}: not UTF-8 text ({error.reason} at byte {error.start}); re-export the model with COLMAP"
        ) from error
    index = 0
    while index < len(lines):
        text = lines[index].strip()
        index += 1
        if not text or text.startswith("#"):
            continue
        if pairs:
            observations = lines[index].strip() if index < len(lines) else ""
            yield index, text, index + 1, observations
            index += 1
        else:
            yield index, text


def check_cameras(path: Path) -> set[int]:
    """The camera ids of cameras.txt, every line checked."""
    ids = set()
    for number, text in _data_lines(path):
        line = _Line(path, number, text)
        camera_id = line.integer("CAMERA_ID")
        model = line.word("MODEL")
        if model not in CAMERA_MODELS:
            raise line.fail(f"MODEL {model!r} is not a COLMAP camera model ({', '.join(CAMERA_MODELS)})")
        line.integer("WIDTH", 1, 1_000_000)
        line.integer("HEIGHT", 1, 1_000_000)
        count, focal_count = CAMERA_MODELS[model]
        if line.remaining() != count:
            raise line.fail(f"camera model {model} has {count} parameters, the line has {line.remaining()}")
        for index in range(count):
            line.number(
                f"PARAMS[{index}]" + (" (focal length)" if index < focal_count else ""), positive=index < focal_count
            )
        if camera_id in ids:
            raise line.fail(f"CAMERA_ID {camera_id} appears twice")
        ids.add(camera_id)
    return ids


def check_images(path: Path, camera_ids: set[int]) -> None:
    """Every image line (id, unit-able quaternion, translation, known camera, name) and observation line."""
    seen = set()
    for number, text, observations_number, observations in _data_lines(path, pairs=True):
        line = _Line(path, number, text)
        image_id = line.integer("IMAGE_ID")
        rotation = [line.number(name) for name in ("QW", "QX", "QY", "QZ")]
        if math.hypot(*rotation) < 1e-12:
            raise line.fail("the rotation quaternion QW QX QY QZ is zero")
        for name in ("TX", "TY", "TZ"):
            line.number(name)
        camera_id = line.integer("CAMERA_ID")
        if camera_ids and camera_id not in camera_ids:
            raise line.fail(f"CAMERA_ID {camera_id} is not in cameras.txt")
        line.word("NAME")
        if image_id in seen:
            raise line.fail(f"IMAGE_ID {image_id} appears twice")
        seen.add(image_id)
        points = _Line(path, observations_number, observations)
        if len(points.tokens) % 3:
            raise points.fail(f"observations come in triples X Y POINT3D_ID, the line has {len(points.tokens)} values")
        for index in range(len(points.tokens) // 3):
            points.number(f"X[{index}]")
            points.number(f"Y[{index}]")
            points.integer(f"POINT3D_ID[{index}]", -1, 2**63 - 1)


def check_points(path: Path) -> None:
    for number, text in _data_lines(path):
        line = _Line(path, number, text)
        line.integer("POINT3D_ID", 0, 2**63 - 1)
        for name in ("X", "Y", "Z"):
            line.number(name)
        for name in ("R", "G", "B"):
            line.integer(name, 0, 255)
        line.number("ERROR")
        if line.remaining() % 2:
            raise line.fail(f"the track comes in pairs IMAGE_ID POINT2D_IDX, the line has {line.remaining()} values")
        for index in range(line.remaining() // 2):
            line.integer(f"IMAGE_ID[{index}]")
            line.integer(f"POINT2D_IDX[{index}]")


def check_text_model(model: Path) -> None:
    """Check the text files of a COLMAP model folder (those present; binary models are pycolmap's)."""
    if not (model / "cameras.txt").is_file() or (model / "cameras.bin").is_file():
        return
    camera_ids = check_cameras(model / "cameras.txt")
    if (model / "images.txt").is_file():
        check_images(model / "images.txt", camera_ids)
    if (model / "points3D.txt").is_file():
        check_points(model / "points3D.txt")
