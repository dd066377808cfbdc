"""In-memory datasets: views (one LDR image at one exposure, optional HDR) grouped in splits."""

import dataclasses
import hashlib
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from mono_hdr_plugin.core.backbone import SceneInfo
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.data.errors import DatasetError


def check_hdr_ground_truth(hdr, label: str) -> str | None:
    """HDR ground truth [H, W, 3] (tensor or array): raise DatasetError for negative values, which no
    radiance has; return why it carries no HDR information (all zero, one value everywhere), or None."""
    flat = torch.as_tensor(hdr).reshape(-1, 3)
    negative = flat < 0
    if negative.any():
        raise DatasetError(
            f"{label}: HDR ground truth has {int(negative.any(-1).sum())} pixel(s) with negative "
            f"values (down to {float(flat.min()):.4g}); radiance is never negative: export it as "
            "linear, unclamped values (clamp small filter ringing to 0)"
        )
    if not bool((flat != 0).any()):
        return "is all zero"
    if bool((flat == flat[0]).all()):
        return f"has one value {tuple(round(v, 6) for v in flat[0].tolist())} at every pixel"
    return None


def without_uninformative_hdr(views: list["View"]) -> tuple[list["View"], list[str]]:
    """The views with HDR ground truth that carries no HDR information removed (never trained on or
    scored), and a note per view that lost it."""
    kept, notes = [], []
    for view in views:
        reason = check_hdr_ground_truth(view.hdr, view.name or str(view.view_id)) if view.hdr is not None else None
        if reason:
            notes.append(f"{view.name or view.view_id} {reason}")
            view = dataclasses.replace(view, hdr=None)
        kept.append(view)
    return kept, notes


def warn_uninformative_hdr(scene: str, notes: list[str]) -> None:
    listing = "; ".join(notes[:5]) + (f"; and {len(notes) - 5} more" if len(notes) > 5 else "")
    warnings.warn(
        f"scene {scene!r}: the HDR ground truth of {len(notes)} view(s) carries no HDR information and is "
        f"not used for training or HDR metrics ({listing}); re-export it if it should",
        stacklevel=3,
    )


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
            raise ValueError(
                f"{label}: image has shape {tuple(self.image.shape)}, camera expects "
                f"{expected}; resize the image or fix the intrinsics"
            )
        if not (self.exposure > 0 and torch.isfinite(torch.tensor(self.exposure))):
            raise ValueError(f"{label}: exposure time must be a positive number of seconds, got {self.exposure}")
        if self.hdr is not None and tuple(self.hdr.shape) != expected:
            raise ValueError(f"{label}: HDR ground truth has shape {tuple(self.hdr.shape)}, expected {expected}")
        # NaN in the data would make every step on this view non-finite, skipped by the trainer
        for what, pixels in (("image", self.image), ("HDR ground truth", self.hdr)):
            if pixels is not None and not torch.isfinite(pixels).all():
                raise ValueError(f"{label}: {what} contains NaN or Inf; repair or drop the file")
        if self.hdr is not None:
            check_hdr_ground_truth(self.hdr, label)


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
        # All-zero or constant HDR ground truth would be "learned" and scored: keep it out of both.
        self.train, train_notes = without_uninformative_hdr(self.train)
        self.test, test_notes = without_uninformative_hdr(self.test)
        if train_notes or test_notes:
            warn_uninformative_hdr(self.name, train_notes + test_notes)

    def fingerprint(self) -> str:
        """A digest of everything training reads from the data, view by view: name, exposure, camera,
        photo and HDR ground truth. `--resume` compares it to refuse continuing on other data."""
        digest = hashlib.sha256()
        for split, views in (("train", self.train), ("test", self.test)):
            for view in views:
                camera = view.camera
                digest.update(
                    f"{split}|{view.name}|{view.exposure!r}|{camera.width}x{camera.height}|{camera.fx!r}|"
                    f"{camera.fy!r}|{camera.cx!r}|{camera.cy!r}|{camera.near!r}|{camera.far!r}|".encode()
                )
                for tensor in (camera.c2w, view.image, view.hdr):
                    if tensor is not None:
                        digest.update(tensor.detach().float().contiguous().numpy().tobytes())
        return digest.hexdigest()

    @property
    def train_exposures(self) -> list[float]:
        return sorted({v.exposure for v in self.train})

    @property
    def test_exposures(self) -> list[float]:
        return sorted({v.exposure for v in self.test})

    def scene_info(self) -> SceneInfo:
        return SceneInfo(
            bounds_min=self.bounds_min,
            bounds_max=self.bounds_max,
            train_cameras=[v.camera for v in self.train],
            points=self.points,
            point_colors=self.point_colors,
            unbounded=bool(self.metadata.get("unbounded", False)),
        )
