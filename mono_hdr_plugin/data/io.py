"""Image files in and out: PNG (8 and 16 bit), JPEG, OpenEXR.

Every reader returns float32 [H, W, 3] (LDR in [0, 1], HDR linear); alpha is dropped, since
the HDR-NeRF data stores RGBA PNGs that are used without compositing. Every writer writes a
temporary file next to the target and renames it, so a crash never leaves half a file.

16-bit PNGs go through Mitsuba's libpng bitmap reader: Pillow silently reads 16-bit RGB PNGs
as 8-bit, one of the official code's defects. Writing half-float EXR raises on values above
the float16 maximum (65504) rather than clamping, because a clamped HDR ground truth is
silently wrong; write float32 (half=False) or scale the image instead.
"""

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from mono_hdr_plugin.data.errors import DatasetError, as_os_error, missing

FLOAT16_MAX = 65504.0
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# In a PNG, the IHDR chunk follows the 8-byte signature; its bit depth is byte 24 of the file.
PNG_BIT_DEPTH_OFFSET = 24


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, durable: bool = False):
    """Yield a temporary path beside `path` (same suffix); rename it onto `path` on success.

    On failure `path` keeps its previous content and the temporary file is removed; a file-system
    error names `path`, also when a library reported it as text (OpenEXR's "No space left on device").
    `durable`: flush the file and the folder to disk, so the rename survives a power cut.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.stem}.tmp-{os.getpid()}{path.suffix}")
    try:
        yield temporary
        if durable:
            _fsync(temporary)
        os.replace(temporary, path)
        if durable:
            _fsync(path.parent)
    except Exception as error:
        os_error = as_os_error(error, path)
        if os_error is None:
            raise
        raise OSError(os_error.errno, os_error.strerror, str(path)) from error  # named: the file being written
    finally:
        temporary.unlink(missing_ok=True)


@contextlib.contextmanager
def utf8_path(path: str | os.PathLike) -> Iterator[Path]:
    """`path`, or where its name is not UTF-8 (POSIX accepts any bytes), a symbolic link to it under a
    temporary UTF-8 name: COLMAP takes UTF-8 paths only. Files and folders, read or written."""
    path = Path(path)
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        with tempfile.TemporaryDirectory(prefix="mono-hdr-link.") as folder:
            link = Path(folder) / "link"
            os.symlink(os.fsencode(path.absolute()), link)
            yield link
    else:
        yield path


def _fsync(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def write_json(path: str | os.PathLike, data) -> None:
    """JSON written atomically; values JSON lacks (paths) as strings; +inf PSNR (identical images)
    as Infinity."""
    with atomic_path(path) as temporary:
        temporary.write_text(json.dumps(data, indent=2, default=str) + "\n")


def _existing(path: str | os.PathLike) -> Path:
    """`path`, checked to be a readable file, so a decoder's failure means a damaged file."""
    path = Path(path)
    if path.is_dir():
        raise DatasetError(f"{path}: is a folder, not an image file; check the dataset's file names")
    if not path.is_file():
        raise missing(path, "check the path, or re-export the dataset")
    check_readable(path)
    return path


def check_readable(path: Path) -> None:
    """A file that exists but cannot be opened is a permission problem, not a damaged file: say so."""
    try:
        with open(path, "rb"):
            pass
    except OSError as error:
        raise DatasetError(
            f"{path}: cannot be opened ({error.strerror}); fix its permissions (e.g. `chmod u+r`)"
        ) from error


def _to_rgb(pixels: np.ndarray, path: Path) -> np.ndarray:
    """[H, W, C] with C in {3, 4} -> [H, W, 3]; any other channel count is an error."""
    if pixels.ndim != 3 or pixels.shape[2] not in (3, 4):
        channels = 1 if pixels.ndim == 2 else pixels.shape[-1]
        raise DatasetError(
            f"{path}: image has {channels} channel(s), expected RGB or RGBA; "
            "convert it to RGB (e.g. `convert in.png -type TrueColor out.png`)"
        )
    return pixels[..., :3]


def _png_bit_depth(path: Path) -> int | None:
    """Bit depth from a PNG header, or None when the file is not a PNG."""
    with open(path, "rb") as handle:
        header = handle.read(PNG_BIT_DEPTH_OFFSET + 1)
    if not header.startswith(PNG_SIGNATURE) or len(header) <= PNG_BIT_DEPTH_OFFSET:
        return None
    return header[PNG_BIT_DEPTH_OFFSET]


def _corrupt(path: Path, error: Exception) -> DatasetError:
    reason = " ".join(str(error).split())  # libpng's reason ends in a newline
    return DatasetError(
        f"{path}: cannot decode the image ({reason}); the file is truncated or corrupt: copy or export it again"
    )


def _read_png16(path: Path) -> np.ndarray:
    import mitsuba  # libpng keeps all 16 bits; imported here because it is slow to import

    stream = mitsuba.MemoryStream()  # Mitsuba takes UTF-8 paths only: Python reads the file's bytes
    stream.write(path.read_bytes())
    stream.seek(0)
    try:
        pixels = np.array(mitsuba.Bitmap(stream))
    except Exception as error:
        raise _corrupt(path, error) from error
    return _to_rgb(pixels, path).astype(np.float32) / 65535.0


def _read_with_pillow(path: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as opened:
            opened.load()  # decode now: a truncated file fails here, not later
            image = opened.convert("RGBA") if opened.mode in ("P", "PA") else opened
            pixels = np.asarray(image)
    except (OSError, UnidentifiedImageError, SyntaxError) as error:
        raise _corrupt(path, error) from error
    if pixels.dtype != np.uint8:
        raise DatasetError(
            f"{path}: unsupported pixel type {pixels.dtype} ({image.mode}); save it as 8- or 16-bit RGB PNG or JPEG"
        )
    return _to_rgb(pixels, path).astype(np.float32) / 255.0


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An LDR image (PNG 8/16 bit or JPEG) as float32 [H, W, 3] in [0, 1], alpha dropped."""
    path = _existing(path)
    if _png_bit_depth(path) == 16:
        return _read_png16(path)
    return _read_with_pillow(path)


def _check_image(image: np.ndarray, what: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise DatasetError(f"{what}: expected an [H, W, 3] image, got shape {image.shape}")
    if not np.isfinite(image).all():
        raise DatasetError(f"{what}: image contains NaN or Inf; fix the values before writing")
    return image


def write_png(path: str | os.PathLike, image: np.ndarray, bits: int = 8) -> None:
    """Write float [H, W, 3] in [0, 1] (clipped) as an 8- or 16-bit RGB PNG."""
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, got {bits}")
    image = _check_image(image, str(path))
    levels = 2**bits - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    pixels = np.ascontiguousarray(np.round(np.clip(image, 0.0, 1.0) * levels).astype(dtype))
    with atomic_path(path) as temporary:
        if bits == 8:
            from PIL import Image

            Image.fromarray(pixels, mode="RGB").save(temporary, format="PNG")
        else:
            import mitsuba

            stream = mitsuba.MemoryStream()  # written by Python: Mitsuba takes UTF-8 paths only
            mitsuba.Bitmap(pixels, pixel_format=mitsuba.Bitmap.PixelFormat.RGB).write(
                stream, mitsuba.Bitmap.FileFormat.PNG
            )
            stream.seek(0)
            temporary.write_bytes(stream.read(stream.size()))


def _exr_rgb(channels: dict, path: Path) -> np.ndarray:
    """Pick RGB out of an OpenEXR channel dict (interleaved 'RGB'/'RGBA' or separate R, G, B)."""
    for name in ("RGB", "RGBA"):
        if name in channels:
            return channels[name].pixels[..., :3]
    if all(c in channels for c in "RGB"):
        return np.stack([channels[c].pixels for c in "RGB"], -1)
    raise DatasetError(f"{path}: EXR has channels {sorted(channels)}, expected R, G, B; re-export it as an RGB EXR")


def read_exr(path: str | os.PathLike) -> np.ndarray:
    """A linear HDR image from an OpenEXR file as float32 [H, W, 3]; NaN/Inf is an error."""
    import OpenEXR

    path = _existing(path)
    try:
        channels = OpenEXR.File(os.fsencode(path)).channels()  # bytes: any folder name the OS accepts
    except Exception as error:
        raise DatasetError(
            f"{path}: cannot read the EXR ({error}); the file is truncated or corrupt: export it again"
        ) from error
    pixels = _exr_rgb(channels, path).astype(np.float32)
    bad = ~np.isfinite(pixels)
    if bad.any():
        raise DatasetError(
            f"{path}: {int(bad.any(-1).sum())} pixel(s) are NaN or Inf; "
            "re-render or repair the file (e.g. replace them by neighbours)"
        )
    return pixels


def write_exr(path: str | os.PathLike, image: np.ndarray, half: bool = False) -> None:
    """Write linear float [H, W, 3] as an RGB OpenEXR (float32, or float16 when `half`).

    Raises DatasetError when `half` and a value exceeds 65504 (the float16 maximum).
    """
    import OpenEXR

    image = _check_image(image, str(path))
    if half and np.abs(image).max(initial=0.0) > FLOAT16_MAX:
        raise DatasetError(
            f"{path}: values up to {np.abs(image).max():.4g} overflow half "
            f"floats (max {FLOAT16_MAX}); write with half=False or scale the image"
        )
    # OpenEXR writes wrong pixels from non-contiguous arrays, so always pass a fresh copy.
    pixels = np.ascontiguousarray(image, dtype=np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as temporary:
        OpenEXR.File(header, {"RGB": pixels}).write(os.fsencode(temporary))


def write_ply_vertices(path: str | os.PathLike, vertices: np.ndarray) -> Path:
    """A PLY file whose one "vertex" element holds the structured array `vertices` (atomic)."""
    from plyfile import PlyData, PlyElement  # only exports need it

    with atomic_path(path) as temporary:
        PlyData([PlyElement.describe(vertices, "vertex")]).write(str(temporary))
    return Path(path)


def read_ply_vertices(path: str | os.PathLike, kind: str):
    """The "vertex" element of a PLY file; errors name the file and the `kind` of PLY expected."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PLY file at {path}")
    try:
        return PlyData.read(str(path))["vertex"]
    except (KeyError, ValueError) as error:
        raise ValueError(f"{path} is not a {kind} PLY (need a 'vertex' element): {error}") from error
