"""Every photo a dataset holds, before an exposure protocol picks the ones a run uses.

Layout readers and the studio produce a `CapturedScene`: per view one camera (OpenCV
camera-to-world), its split, and its photos at one or more exposures, loaded lazily so a
single-exposure run never decodes the other exposures. Layout writers consume the same.
"""

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from mono_hdr_plugin.core.cameras import Camera

ImageSource = Callable[[], np.ndarray]
"""Returns a float32 [H, W, 3] image when called (reads the file, or returns an array)."""


def constant(image: np.ndarray) -> ImageSource:
    """An ImageSource for an image already in memory."""
    return lambda: image


@dataclass(frozen=True)
class ImageFile:
    """An ImageSource that reads `path` with `reader`; the path names the file in messages."""

    path: Path
    reader: Callable[[Path], np.ndarray]

    def __call__(self) -> np.ndarray:
        return self.reader(self.path)


@dataclass
class Shot:
    """One photo: exposure time in seconds and where its pixels come from.

    `downscaled` maps a factor N to the same photo stored N times smaller beside it (LLFF's images_N/):
    --downscale N reads that file, as every LLFF loader does, instead of averaging the full photo.
    """

    exposure: float
    image: ImageSource
    name: str
    downscaled: dict[int, ImageSource] = field(default_factory=dict)


@dataclass
class CapturedView:
    """One camera pose and all its photos, sorted by exposure."""

    view_id: int
    camera: Camera
    split: Literal["train", "test"]
    shots: list[Shot]
    hdr: ImageSource | None = None
    name: str = ""


@dataclass
class CapturedScene:
    """All views of a scene plus its bounds and optional initial points (world coordinates)."""

    name: str
    views: list[CapturedView]
    bounds_min: torch.Tensor
    bounds_max: torch.Tensor
    points: torch.Tensor | None = None
    point_colors: torch.Tensor | None = None
    metadata: dict = field(default_factory=dict)

    @property
    def exposure_levels(self) -> list[float]:
        """Distinct exposure times over all photos, ascending (equal within 0.1 %)."""
        levels: list[float] = []
        for exposure in sorted(shot.exposure for view in self.views for shot in view.shots):
            if not levels or not np.isclose(exposure, levels[-1], rtol=1e-3, atol=0):
                levels.append(exposure)
        return levels


def bounds_from_points(points: np.ndarray, margin: float = 0.02) -> tuple[torch.Tensor, torch.Tensor]:
    """Axis-aligned box around [N, 3] points, grown by `margin` of its size on each side."""
    low, high = points.min(0), points.max(0)
    pad = margin * (high - low).clip(min=1e-3)
    return torch.tensor(low - pad, dtype=torch.float32), torch.tensor(high + pad, dtype=torch.float32)


def bounds_from_cameras(cameras: list[Camera]) -> tuple[torch.Tensor, torch.Tensor]:
    """A box for scenes with no points: camera centres plus the point all cameras look at.

    The look-at point is the least-squares closest point to every optical axis; for
    near-parallel (forward-facing) axes it falls back to one rig radius ahead of the cameras.
    """
    centres = np.stack([c.center.double().numpy() for c in cameras])
    axes = np.stack([c.c2w[:3, 2].double().numpy() for c in cameras])
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    system = projectors.sum(0)
    radius = max(np.linalg.norm(centres - centres.mean(0), axis=1).max(), 1.0)
    if np.linalg.cond(system) < 1e6:
        focus = np.linalg.solve(system, np.einsum("nij,nj->i", projectors, centres))
    else:
        focus = centres.mean(0) + radius * axes.mean(0)
    reach = np.linalg.norm(centres - focus, axis=1).max()
    corners = np.concatenate([centres, focus[None] - reach, focus[None] + reach])
    return bounds_from_points(corners, margin=0.0)
