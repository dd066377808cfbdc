"""HDR-NeRF real layout (docs/datasets.md), read and written.

    poses_bounds_exps.npy   [N, 18]: LLFF [R | t | hwf] (3x5, axes down/right/back), near, far,
                            exposure seconds; rows follow the string-sorted input_images
    input_images/           <view>_<e>.<ext>, e.g. 000_0.jpg .. 034_4.jpg

Views are ordered by their numeric view token; even views train, odd views test (HDR-NeRF's
split; the official Mono code's with-replacement random split is not reproduced).
"""

import functools
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
    camera_from,
    check_exposure,
    check_finite,
    check_one_size,
    image_size,
    natural_key,
    read_pose_source,
    split_view_exposure,
    write_pose_source,
)

POSES_FILE = "poses_bounds_exps.npy"
IMAGE_FOLDER = "input_images"
COLUMNS = 18


def detect(folder: Path) -> bool:
    return (folder / POSES_FILE).is_file()


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


def _load_rows(folder: Path, names: list[str]) -> np.ndarray:
    path = folder / POSES_FILE
    try:
        rows = np.load(path)
    except (ValueError, OSError, EOFError) as error:
        raise DatasetError(f"{path}: cannot read the array ({error}); regenerate it") from error
    if rows.ndim != 2 or rows.shape[1] != COLUMNS:
        raise DatasetError(
            f"{path}: shape {rows.shape}, expected (images, {COLUMNS}) (pose 15, near, far, exposure); regenerate it"
        )
    if len(rows) != len(names):
        raise DatasetError(
            f"{path}: {len(rows)} rows but {folder / IMAGE_FOLDER} has {len(names)} "
            "images; the poses/exposures are out of step with the images: "
            "restore the missing images or regenerate the file"
        )
    return check_finite(rows, path, "a pose, bound or exposure")


def _group_by_view(images: Path, names: list[str], rows: np.ndarray) -> dict[str, list[tuple[str, np.ndarray]]]:
    """The (name, row) pairs of each view token, from names <view>_<e>.<ext>."""
    groups: dict[str, list[tuple[str, np.ndarray]]] = {}
    for name, row in zip(names, rows):
        parsed = split_view_exposure(name)
        if parsed is None:
            raise DatasetError(
                f"{images / name}: expected a name <view>_<exposure index>.<ext> like 000_0.jpg; rename the file"
            )
        groups.setdefault(parsed[0], []).append((name, row))
    return groups


def _view_camera(folder: Path, name: str, row: np.ndarray, width: int, height: int) -> Camera:
    """The camera of a view's first row: LLFF pose, hwf focal length rescaled to the photos, near and far."""
    pose = row[:15].reshape(3, 5)
    if not (pose[:, 4] > 0).all():
        raise DatasetError(
            f"{folder / POSES_FILE} row of {name}: image height, width and focal length "
            f"(columns 4, 9 and 14) must be positive, got {', '.join(f'{v:g}' for v in pose[:, 4])}; "
            "regenerate the file"
        )
    focal = pose[2, 4] * width / pose[1, 4]  # hwf is for the original size; photos may be smaller
    return camera_from(
        f"{folder / POSES_FILE} row of {name}",
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


def _view_shots(folder: Path, group: list[tuple[str, np.ndarray]]) -> list[Shot]:
    """A view's photos with the exposures of their rows, shortest exposure first."""
    shots = [
        Shot(
            check_exposure(row[17], f"{folder / POSES_FILE} row of {name}"),
            functools.partial(read_image, folder / IMAGE_FOLDER / name),
            name,
        )
        for name, row in group
    ]
    return sorted(shots, key=lambda s: s.exposure)


def read(folder: Path) -> CapturedScene:
    """Every photo of an HDR-NeRF real scene (no HDR ground truth)."""
    images = folder / IMAGE_FOLDER
    if not images.is_dir():
        raise missing(images, f"the HDR-NeRF real layout keeps its photos in {IMAGE_FOLDER}/")
    # Rows pair with the string-sorted names, as the official loader's sorted(os.listdir).
    names = sorted(p.name for p in images.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    rows = _load_rows(folder, names)
    groups = _group_by_view(images, names, rows)
    width, height = check_one_size({images / n: image_size(images / n) for n in names}, images)
    views = []
    for view_id, token in enumerate(sorted(groups, key=natural_key)):
        first_name, first_row = groups[token][0]
        views.append(
            CapturedView(
                view_id=view_id,
                camera=_view_camera(folder, first_name, first_row, width, height),
                split="train" if view_id % 2 == 0 else "test",
                shots=_view_shots(folder, groups[token]),
                name=token,
            )
        )
    bounds_min, bounds_max = bounds_from_cameras([v.camera for v in views])
    return CapturedScene(
        name=folder.name,
        views=views,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        metadata={"source": str(folder), "layout": "hdr-nerf-real", "poses": read_pose_source(folder)},
    )


def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
    """Write every photo as input_images/<view:03d>_<e>.png plus poses_bounds_exps.npy."""
    folder = Path(folder)
    entries = []
    for index, view in enumerate(scene.views):
        camera = view.camera
        hwf = np.array([[camera.height], [camera.width], [camera.fx]])
        pose = np.concatenate([opencv_to_llff(camera.c2w.double().numpy()), hwf], axis=1)
        for e, shot in enumerate(view.shots):
            name = f"{index:03d}_{e}.png"
            write_png(folder / IMAGE_FOLDER / name, shot.image(), bits=bits)
            entries.append((name, [*pose.ravel(), camera.near, camera.far, shot.exposure]))
    rows = np.array([row for _, row in sorted(entries)])
    with atomic_path(folder / POSES_FILE) as temporary, open(temporary, "wb") as handle:
        np.save(handle, rows)
    write_pose_source(scene.metadata, folder)


@register_layout("hdr-nerf-real")
class HdrNerfRealLayout(DatasetLayout):
    description = "poses_bounds_exps.npy + input_images/ (HDR-NeRF real, LLFF)"
    writable = True
    detect = staticmethod(detect)
    read = staticmethod(read)
    write = staticmethod(write)
