"""HDR-NeRF real layout (docs/datasets.md), read and written: the LLFF layout (llff.py) with exposures.

    poses_bounds_exps.npy   [N, 18]: LLFF [R | t | hwf] (3x5, axes down/right/back), near, far,
                            exposure seconds; rows follow the string-sorted input_images
    input_images/           <view>_<e>.<ext>, e.g. 000_0.jpg .. 034_4.jpg

Views are ordered by their numeric view token; even views train, odd views test (HDR-NeRF's
split; the official Mono code's with-replacement random split is not reproduced).
"""

import functools
from pathlib import Path

import numpy as np

from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot, bounds_from_cameras
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import atomic_path, read_image, write_png
from mono_hdr_plugin.data.layouts.base import DatasetLayout, register_layout
from mono_hdr_plugin.data.layouts.common import (
    check_exposure,
    check_one_size,
    image_size,
    natural_key,
    read_pose_source,
    split_view_exposure,
    write_pose_source,
)
from mono_hdr_plugin.data.layouts.llff import (
    EXPOSURES_POSES_FILE,
    PoseFile,
    image_names,
    llff_camera,
    llff_row,
    load_pose_rows,
)

POSES_FILE = EXPOSURES_POSES_FILE
IMAGE_FOLDER = "input_images"
POSE_FILE = PoseFile(POSES_FILE, 18, "pose 15, near, far, exposure", "a pose, bound or exposure")


def detect(folder: Path) -> bool:
    return (folder / POSES_FILE).is_file()


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
    names = image_names(images)
    rows = load_pose_rows(folder, POSE_FILE, names, images)
    groups = _group_by_view(images, names, rows)
    width, height = check_one_size({images / n: image_size(images / n) for n in names}, images)
    views = []
    for view_id, token in enumerate(sorted(groups, key=natural_key)):
        first_name, first_row = groups[token][0]
        views.append(
            CapturedView(
                view_id=view_id,
                camera=llff_camera(f"{folder / POSES_FILE} row of {first_name}", first_row, width, height),
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
        for e, shot in enumerate(view.shots):
            name = f"{index:03d}_{e}.png"
            write_png(folder / IMAGE_FOLDER / name, shot.image(), bits=bits)
            entries.append((name, [*llff_row(view.camera), shot.exposure]))
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
