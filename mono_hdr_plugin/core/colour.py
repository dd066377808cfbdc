"""The standard response curves, one implementation each.

sRGB is written once, in torch (`srgb_encode`, `srgb_decode`): the viewer and the display scale
run it on renders, and numpy callers (RAW photos, the studio camera, the default response table)
run the same function on a float64 tensor view of their array. BT.709, which only numpy callers
need, comes from colour-science, called here and nowhere else.
"""

from typing import Literal

import numpy as np
import torch
from torch import Tensor

ResponseCurve = Literal["srgb", "bt709"]
RESPONSE_CURVES: tuple[str, ...] = ("srgb", "bt709")


def srgb_encode(linear: Tensor) -> Tensor:
    """The sRGB transfer curve (IEC 61966-2-1) of linear values, clipped to [0, 1] first."""
    return _srgb_curve(linear.clamp(0.0, 1.0))


def srgb_decode(encoded: Tensor) -> Tensor:
    """Inverse of srgb_encode on [0, 1]."""
    return _srgb_inverse(encoded.clamp(0.0, 1.0))


def _srgb_curve(linear: Tensor) -> Tensor:
    """The sRGB curve without clipping: a camera's response may run past 1 before its sensor clips."""
    return torch.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


def _srgb_inverse(encoded: Tensor) -> Tensor:
    return torch.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4)


def encode_curve(linear: np.ndarray, curve: ResponseCurve) -> np.ndarray:
    """Linear values through a standard response curve (not clipped), as float64."""
    if curve == "srgb":
        return _srgb_curve(torch.as_tensor(np.asarray(linear), dtype=torch.float64)).numpy()
    import colour

    return np.asarray(colour.cctf_encoding(np.asarray(linear, np.float64), function="ITU-R BT.709"), np.float64)


def decode_curve(encoded: np.ndarray, curve: ResponseCurve) -> np.ndarray:
    """Inverse of `encode_curve` (not clipped), as float64."""
    if curve == "srgb":
        return _srgb_inverse(torch.as_tensor(np.asarray(encoded), dtype=torch.float64)).numpy()
    import colour

    return np.asarray(colour.cctf_decoding(np.asarray(encoded, np.float64), function="ITU-R BT.709"), np.float64)
