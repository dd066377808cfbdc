"""Minimal DNG files (a Bayer mosaic plus the tags LibRaw needs), written with tifffile."""

from fractions import Fraction
from pathlib import Path

import colour
import numpy as np
import tifffile

BLACK, WHITE = 512, 16383
XYZ_TO_SRGB = colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB
"""As the DNG ColorMatrix1 (XYZ -> camera), it makes the camera's colour space linear sRGB."""


def _rationals(values, denominator: int = 1_000_000) -> tuple[int, ...]:
    return tuple(part for value in values for part in (int(round(value * denominator)), denominator))


def write_dng(path: Path, linear: np.ndarray, exposure: Fraction | None = None, f_number: float = 2.8) -> Path:
    """A DNG whose demosaiced, white-balanced sRGB pixels are `linear` [H, W, 3] (clipped to [0, 1]).

    RGGB mosaic, 14-bit with black level 512; H and W must be even.
    """
    linear = np.clip(linear, 0.0, 1.0)
    mosaic = np.empty(linear.shape[:2])
    mosaic[0::2, 0::2] = linear[0::2, 0::2, 0]
    mosaic[0::2, 1::2] = linear[0::2, 1::2, 1]
    mosaic[1::2, 0::2] = linear[1::2, 0::2, 1]
    mosaic[1::2, 1::2] = linear[1::2, 1::2, 2]
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50708, "s", 0, "Mono-HDR TestCam", True),  # UniqueCameraModel
        (33421, "H", 2, (2, 2), True),
        (33422, "B", 4, (0, 1, 1, 2), True),  # CFA repeat, RGGB
        (50714, "H", 1, BLACK, True),
        (50717, "H", 1, WHITE, True),
        (50721, "2i", 9, _rationals(XYZ_TO_SRGB.ravel()), True),
        (50778, "H", 1, 21, True),  # D65
        (50728, "2I", 3, _rationals((1, 1, 1)), True),  # AsShotNeutral: no white balance
        (33437, "2I", 1, _rationals([f_number], 10), True),
    ]
    if exposure is not None:
        tags.append((33434, "2I", 1, (exposure.numerator, exposure.denominator), True))
    pixels = np.round(mosaic * (WHITE - BLACK) + BLACK).astype(np.uint16)
    tifffile.imwrite(path, pixels, photometric=32803, extratags=tags, subfiletype=0)
    return path
