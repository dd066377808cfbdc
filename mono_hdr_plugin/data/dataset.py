"""In-memory datasets: views (one LDR image at one exposure, optional HDR) grouped in splits."""

from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from mono_hdr_plugin.backbone import SceneInfo
from mono_hdr_plugin.cameras import Camera


@dataclass
class View:
    """One LDR photo: camera, image [H, W, 3] in [0, 1], exposure time in seconds.

    view_id groups photos of the same camera pose taken at several exposures; hdr is the
    linear HDR ground truth [H, W, 3] where the dataset has one.
    """

    camera: Camera
    image: Tensor
    exposure: float
    view_id: int
    name: str = ""
    hdr: Tensor | None = None
    stem: str = ""
    """File-name stem of this view's renders, `<view>_t<level>` (`r_0_t3`: view r_0 at exposure
    level t3); empty: derived from name or view_id."""

    def __post_init__(self):
        if not self.stem:
            self.stem = Path(self.name).stem if self.name else f"view_{self.view_id:03d}"
        label = self.name or f"view {self.view_id}"
        expected = (self.camera.height, self.camera.width, 3)
        if tuple(self.image.shape) != expected:
            raise ValueError(f"{label}: image has shape {tuple(self.image.shape)}, camera expects "
                             f"{expected}; resize the image or fix the intrinsics")
        if not (self.exposure > 0 and torch.isfinite(torch.tensor(self.exposure))):
            raise ValueError(f"{label}: exposure time must be a positive number of seconds, "
                             f"got {self.exposure}")
        if self.hdr is not None and tuple(self.hdr.shape) != expected:
            raise ValueError(f"{label}: HDR ground truth has shape {tuple(self.hdr.shape)}, "
                             f"expected {expected}")
        # NaN in the data would make every step on this view non-finite, skipped by the trainer
        for what, pixels in (("image", self.image), ("HDR ground truth", self.hdr)):
            if pixels is not None and not torch.isfinite(pixels).all():
                raise ValueError(f"{label}: {what} contains NaN or Inf; repair or drop the file")


@dataclass
class SceneData:
    """A whole scene: train and test views, scene bounds and optional initial points."""

    name: str
    train: list[View]
    test: list[View]
    bounds_min: Tensor
    bounds_max: Tensor
    points: Tensor | None = None
    point_colors: Tensor | None = None
    metadata: dict = field(default_factory=dict)

    def __post_init__(self):
        if not self.train:
            raise ValueError(f"scene {self.name!r} has no training views")

    @property
    def train_exposures(self) -> list[float]:
        return sorted({v.exposure for v in self.train})

    @property
    def test_exposures(self) -> list[float]:
        return sorted({v.exposure for v in self.test})

    def scene_info(self) -> SceneInfo:
        return SceneInfo(bounds_min=self.bounds_min, bounds_max=self.bounds_max,
                         train_cameras=[v.camera for v in self.train],
                         points=self.points, point_colors=self.point_colors)
