"""LLFF layout (docs/datasets.md), read and written: the NeRF paper's real forward-facing scenes.

    poses_bounds.npy   [N, 17]: LLFF [R | t | hwf] (3x5, axes down/right/back), near, far;
                       rows follow the string-sorted images/
    images/            the photos, any names
    images_N/          (optional) the same photos N times smaller, in the same order (LLFF's
                       minify): --downscale N reads them, as NeRF's load_llff_data does

Every 8th view (i % 8 == 0) is held out for testing, the protocol of the NeRF real-scene tables.
The layout has no exposure times: each photo reads as 1 s and is named in the scene's
metadata["unknown_exposures"], for the trainer to learn (as process-data's null exposures).
"""

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot, bounds_from_cameras
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import atomic_path, read_image, write_png
from mono_hdr_plugin.data.layouts.base import DatasetLayout, register_layout
from mono_hdr_plugin.data.layouts.common import (
    IMAGE_SUFFIXES,
    UNKNOWN_EXPOSURE,
    camera_from,
    check_finite,
    check_one_size,
    image_size,
    read_pose_source,
    write_pose_source,
)

POSES_FILE = "poses_bounds.npy"
EXPOSURES_POSES_FILE = "poses_bounds_exps.npy"
"""HDR-NeRF real's pose file (hdr_nerf_real.py): LLFF's rows with an exposure column."""
IMAGE_FOLDER = "images"
TEST_EVERY = 8
"""NeRF's llffhold: views 0, 8, 16, ... are held out."""


def detect(folder: Path) -> bool:
    """poses_bounds.npy, and not HDR-NeRF real's poses_bounds_exps.npy: a scene with exposure times is that
    layout's, even with LLFF's file beside it."""
    return (folder / POSES_FILE).is_file() and not (folder / EXPOSURES_POSES_FILE).is_file()


def llff_to_opencv(pose: np.ndarray) -> np.ndarray:
    """LLFF [3, 4] camera-to-world (columns down, right, back, centre) -> OpenCV [4, 4]."""
    down, right, back, centre = pose[:, 0], pose[:, 1], pose[:, 2], pose[:, 3]
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, down, -back, centre
    return c2w


def opencv_to_llff(c2w: np.ndarray) -> np.ndarray:
    """Inverse of `llff_to_opencv`: OpenCV [4, 4] -> LLFF [3, 4]."""
    right, down, forward, centre = c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3]
    return np.stack([down, right, -forward, centre], axis=1)


def image_names(images: Path) -> list[str]:
    """The photos of an LLFF image folder, string-sorted: the official loaders pair them with the rows so."""
    return sorted(p.name for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)


@dataclass(frozen=True)
class PoseFile:
    """An LLFF-style pose file: its name, its number of columns and, for messages, what they hold."""

    name: str
    columns: int
    content: str
    """The columns, for the message of a wrong shape."""
    values: str
    """What one value is, for the message of one that is not a number."""


POSE_FILE = PoseFile(POSES_FILE, 17, "pose 15, near, far", "a pose or bound")


def load_pose_rows(folder: Path, pose_file: PoseFile, names: list[str], images: Path) -> np.ndarray:
    """The rows of `pose_file` in `folder`, one per photo of `images` (in `names` order), all finite."""
    path = folder / pose_file.name
    try:
        rows = np.load(path)
    except (ValueError, OSError, EOFError) as error:
        raise DatasetError(f"{path}: cannot read the array ({error}); regenerate it") from error
    if rows.ndim != 2 or rows.shape[1] != pose_file.columns:
        raise DatasetError(
            f"{path}: shape {rows.shape}, expected (images, {pose_file.columns}) ({pose_file.content}); regenerate it"
        )
    if len(rows) != len(names):
        raise DatasetError(
            f"{path}: {len(rows)} rows but {images} has {len(names)} images; the poses are out of step "
            "with the images: restore the missing images or regenerate the file"
        )
    return check_finite(rows, path, pose_file.values)


def llff_camera(where: str, row: np.ndarray, width: int, height: int) -> Camera:
    """The camera of one LLFF row: pose, hwf focal length rescaled to the photos' width, near and far."""
    pose = row[:15].reshape(3, 5)
    if not (pose[:, 4] > 0).all():
        raise DatasetError(
            f"{where}: image height, width and focal length (columns 4, 9 and 14) must be positive, "
            f"got {', '.join(f'{v:g}' for v in pose[:, 4])}; regenerate the file"
        )
    focal = pose[2, 4] * width / pose[1, 4]  # hwf is for the original size; photos may be smaller
    return camera_from(
        where,
        c2w=torch.from_numpy(llff_to_opencv(pose[:, :4])).float(),
        fx=focal,
        fy=focal,
        cx=width / 2,
        cy=height / 2,
        width=width,
        height=height,
        near=float(row[15]),
        far=float(row[16]),
    )


def llff_row(camera: Camera) -> list[float]:
    """The 17 values of `camera` in an LLFF pose file: [R | t | hwf] flattened, near, far."""
    hwf = np.array([[camera.height], [camera.width], [camera.fx]])
    pose = np.concatenate([opencv_to_llff(camera.c2w.double().numpy()), hwf], axis=1)
    return [*pose.ravel(), camera.near, camera.far]


def _downscaled_copies(folder: Path, count: int, width: int, height: int) -> dict[int, list[Path]]:
    """The images_N/ folders: N -> their photos in order, each checked to be the full photos N times smaller."""
    copies = {}
    for path in folder.iterdir():
        match = re.fullmatch(r"images_([0-9]{1,4})", path.name)
        if not match or not path.is_dir() or int(match.group(1)) < 2:
            continue
        factor, names = int(match.group(1)), image_names(path)
        if len(names) != count:
            raise DatasetError(
                f"{path}: {len(names)} images but {folder / IMAGE_FOLDER} has {count}; regenerate {path.name}/ "
                f"from {IMAGE_FOLDER}/ or delete it"
            )
        size = check_one_size({path / n: image_size(path / n) for n in names}, path)
        if abs(size[0] * factor - width) >= factor or abs(size[1] * factor - height) >= factor:
            raise DatasetError(
                f"{path}: images are {size[0]}x{size[1]}, but {width}x{height} / {factor} is about "
                f"{width / factor:.0f}x{height / factor:.0f}; regenerate {path.name}/ from {IMAGE_FOLDER}/ or delete it"
            )
        copies[factor] = [path / name for name in names]
    return copies


def read(folder: Path) -> CapturedScene:
    """Every photo of an LLFF scene, one a view, exposures unknown (learned)."""
    images = folder / IMAGE_FOLDER
    if not images.is_dir():
        raise missing(images, f"the LLFF layout keeps its photos in {IMAGE_FOLDER}/")
    names = image_names(images)
    rows = load_pose_rows(folder, POSE_FILE, names, images)
    width, height = check_one_size({images / n: image_size(images / n) for n in names}, images)
    copies = _downscaled_copies(folder, len(names), width, height)
    views = []
    for index, (name, row) in enumerate(zip(names, rows)):
        shot = Shot(
            UNKNOWN_EXPOSURE,
            functools.partial(read_image, images / name),
            name,
            downscaled={factor: functools.partial(read_image, paths[index]) for factor, paths in copies.items()},
        )
        views.append(
            CapturedView(
                view_id=index,
                camera=llff_camera(f"{folder / POSES_FILE} row {index} ({name})", row, width, height),
                split="test" if index % TEST_EVERY == 0 else "train",
                shots=[shot],
                name=Path(name).stem,
            )
        )
    bounds_min, bounds_max = bounds_from_cameras([v.camera for v in views])
    return CapturedScene(
        name=folder.name,
        views=views,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        metadata={
            "source": str(folder),
            "layout": "llff",
            "unknown_exposures": names,
            "poses": read_pose_source(folder),
        },
    )


def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
    """Write images/<view:03d>.png (each view's middle exposure: LLFF holds one photo a view and no
    exposure times) and poses_bounds.npy, last, so a folder is detected only once complete."""
    folder = Path(folder)
    rows = []
    for index, view in enumerate(scene.views):
        write_png(folder / IMAGE_FOLDER / f"{index:03d}.png", view.shots[len(view.shots) // 2].image(), bits=bits)
        rows.append(llff_row(view.camera))
    write_pose_source(scene.metadata, folder)
    with atomic_path(folder / POSES_FILE) as temporary, open(temporary, "wb") as handle:
        np.save(handle, np.array(rows))


@register_layout("llff")
class LlffLayout(DatasetLayout):
    description = "poses_bounds.npy + images/ (+ images_N/) (LLFF, NeRF real scenes; exposures learned)"
    writable = True
    detect = staticmethod(detect)
    read = staticmethod(read)
    write = staticmethod(write)
