"""HDR-NeRF synthetic layout (docs/datasets.md), read and written.

transforms_{train,test}.json   camera_angle_x; frames: file_path (no extension),
                               transform_matrix (OpenGL camera-to-world); optional aabb_scale
                               (instant-ngp: > 1 declares an unbounded scene, e.g. one with a sky;
                               kept as `declared_unbounded`: the photos decide, data/extent.py)
exposure_{train,test}.json     {file_path + "_<e>.png": seconds}
<file_path>_<e>.png            e = 0..4 (t1..t5)
{train,test}_hdr/hdr_%03d.exr  HDR ground truth, index = last "_" token of file_path
"""

import functools
import math
import re
from pathlib import Path

import torch

from mono_hdr_plugin.core.camera_optimizer import EXACT
from mono_hdr_plugin.core.cameras import OPENGL_TO_OPENCV, Camera, focal_from_fov
from mono_hdr_plugin.core.validation import POSITIVE, between
from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, ImageFile, Shot, bounds_from_cameras
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_exr, read_image, write_exr, write_json, write_png
from mono_hdr_plugin.data.layouts.base import DatasetLayout, register_layout
from mono_hdr_plugin.data.layouts.common import (
    camera_from,
    check_exposure,
    check_one_size,
    image_size,
    json_matrix,
    json_name,
    json_number,
    json_object,
    load_json,
)

SPLITS = ("train", "test")
MAX_EXPOSURES = 5
FIELD_OF_VIEW = between(0, math.pi, low_open=True, high_open=True)
"""camera_angle_x, in radians: a pinhole camera sees less than half the sphere."""
UNBOUNDED_AABB_SCALE = 16
"""aabb_scale written for an unbounded scene: instant-ngp's value for content far beyond the cameras."""


def detect(folder: Path) -> bool:
    return (folder / "transforms_train.json").is_file()


def _exr_index(file_path: str) -> int | None:
    token = file_path.split("_")[-1]
    return int(token) if re.fullmatch(r"[0-9]{1,9}", token) else None


def _frame_shots(folder: Path, file_path: str, exposures: dict, exposure_file: Path) -> list[Shot]:
    shots = []
    for e in range(MAX_EXPOSURES):
        key = f"{file_path}_{e}.png"
        exists = (folder / key).is_file()
        if exists and key not in exposures:
            raise DatasetError(
                f"{exposure_file}: no exposure for {key!r}, which exists; add its exposure time (seconds) to the file"
            )
        if key in exposures and not exists:
            raise DatasetError(
                f"{exposure_file}: lists {key!r} but {folder / key} is missing; "
                "the exposure file is out of step with the images: restore the image "
                "or remove the entry"
            )
        if exists:
            exposure = check_exposure(exposures[key], f"{exposure_file} [{key!r}]")
            shots.append(Shot(exposure, functools.partial(read_image, folder / key), key))
    if not shots:
        raise DatasetError(
            f"{folder}: frame {file_path!r} has no image {file_path}_<0..4>.png; "
            "restore the images or remove the frame from the transforms file"
        )
    return shots


def _read_split(folder: Path, split: str, first_view_id: int):
    transforms_file = folder / f"transforms_{split}.json"
    exposure_file = folder / f"exposure_{split}.json"
    transforms = json_object(
        load_json(transforms_file, f"an HDR-NeRF synthetic scene needs {transforms_file.name}"), str(transforms_file)
    )
    exposures = json_object(
        load_json(exposure_file, f"write {exposure_file.name}: {{image name: seconds}}"), str(exposure_file)
    )
    frames = transforms.get("frames")
    if "camera_angle_x" not in transforms or not isinstance(frames, list) or not frames:
        raise DatasetError(f"{transforms_file}: needs 'camera_angle_x' and a non-empty 'frames' list")
    angle = json_number(
        transforms["camera_angle_x"], f"{transforms_file}: camera_angle_x (field of view, radians)", FIELD_OF_VIEW
    )
    aabb_scale = transforms.get("aabb_scale")  # None: the file declares nothing
    if aabb_scale is not None:
        aabb_scale = json_number(aabb_scale, f"{transforms_file}: aabb_scale", POSITIVE)
    poses = []
    first_listed: dict[str, int] = {}  # file_path -> index of the frame that lists it first
    for index, frame in enumerate(frames):
        where = f"{transforms_file}: frames[{index}]"
        frame = json_object(frame, where)
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise DatasetError(f"{where} needs 'file_path' and 'transform_matrix'; add them or remove the frame")
        file_path = json_name(frame["file_path"], f"{where}.file_path")
        if file_path in first_listed:  # one photo would count as two views (and twice in the metrics)
            raise DatasetError(
                f"{where}.file_path {file_path!r} is listed twice (also frames[{first_listed[file_path]}]); "
                "remove the duplicate frame"
            )
        first_listed[file_path] = index
        poses.append((file_path, json_matrix(frame["transform_matrix"], f"{where}.transform_matrix", 4, 4)))
    listed = {f"{file_path}_{e}.png" for file_path, _ in poses for e in range(MAX_EXPOSURES)}
    stray = sorted(set(exposures) - listed)
    if stray:
        raise DatasetError(
            f"{exposure_file}: entries {stray[:3]} match no frame of {transforms_file.name}; "
            "the exposure file is out of step with the frames: regenerate it"
        )
    views = []
    for offset, (file_path, c2w_gl) in enumerate(poses):
        shots = _frame_shots(folder, file_path, exposures, exposure_file)
        views.append((first_view_id + offset, split, file_path, c2w_gl, shots))
    return angle, aabb_scale, views


def _hdr_source(folder: Path, split: str, file_path: str):
    index = _exr_index(file_path)
    path = folder / f"{split}_hdr" / f"hdr_{index:03d}.exr" if index is not None else None
    return ImageFile(path, read_exr) if path is not None and path.is_file() else None


def read(folder: Path) -> CapturedScene:
    """Every photo of an HDR-NeRF synthetic scene; train/test from the two transforms files."""
    angle_train, scale_train, train = _read_split(folder, "train", 0)
    angle_test, scale_test, test = _read_split(folder, "test", len(train))
    if not math.isclose(angle_train, angle_test, rel_tol=1e-6):
        raise DatasetError(
            f"{folder}: camera_angle_x differs between transforms_train.json and "
            "transforms_test.json; both splits must share one camera"
        )
    declared = [scale for scale in (scale_train, scale_test) if scale is not None]
    sizes = {folder / shot.name: image_size(folder / shot.name) for *_, shots in train + test for shot in shots}
    width, height = check_one_size(sizes, folder)
    focal = focal_from_fov(angle_test, width)  # the official loader takes the test file's angle
    views = []
    for view_id, split, file_path, c2w_gl, shots in train + test:
        c2w = torch.from_numpy(c2w_gl).float() @ OPENGL_TO_OPENCV
        camera = camera_from(
            f"{folder / f'transforms_{split}.json'} frame {file_path!r}",
            c2w=c2w,
            fx=focal,
            fy=focal,
            cx=width / 2,
            cy=height / 2,
            width=width,
            height=height,
        )
        views.append(
            CapturedView(
                view_id=view_id,
                camera=camera,
                split=split,
                shots=shots,
                hdr=_hdr_source(folder, split, file_path),
                name=file_path,
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
            "layout": "hdr-nerf-synthetic",
            "poses": EXACT,  # Blender's cameras, as rendered
            "declared_unbounded": None if declared == [] else max(declared) > 1,
        },
    )


def _camera_angle_x(camera: Camera, folder: Path) -> float:
    if not (
        math.isclose(camera.fx, camera.fy, rel_tol=1e-6)
        and math.isclose(camera.cx, camera.width / 2)
        and math.isclose(camera.cy, camera.height / 2)
    ):
        raise DatasetError(
            f"{folder}: the HDR-NeRF synthetic layout stores only camera_angle_x, so "
            "cameras need fx == fy and a centred principal point; write --layout hdr-gs"
        )
    return 2 * math.atan(0.5 * camera.width / camera.fx)


def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
    """Write every photo of `scene` in the HDR-NeRF synthetic layout; frames count from 0 per split."""
    folder = Path(folder)
    angle = _camera_angle_x(scene.views[0].camera, folder)
    for split in SPLITS:
        frames, exposures = [], {}
        for index, view in enumerate(v for v in scene.views if v.split == split):
            file_path = f"./{split}/r_{index}"
            for e, shot in enumerate(view.shots):
                write_png(folder / f"{file_path}_{e}.png", shot.image(), bits=bits)
                exposures[f"{file_path}_{e}.png"] = shot.exposure
            if view.hdr is not None:
                write_exr(folder / f"{split}_hdr" / f"hdr_{index:03d}.exr", view.hdr())
            c2w_gl = view.camera.c2w.double() @ OPENGL_TO_OPENCV.double()
            frames.append({"file_path": file_path, "transform_matrix": c2w_gl.tolist()})
        unbounded = scene.metadata.get("unbounded", scene.metadata.get("declared_unbounded"))
        extent = {"aabb_scale": UNBOUNDED_AABB_SCALE} if unbounded else {}
        write_json(folder / f"transforms_{split}.json", {"camera_angle_x": angle, **extent, "frames": frames})
        write_json(folder / f"exposure_{split}.json", exposures)


@register_layout("hdr-nerf-synthetic")
class HdrNerfSyntheticLayout(DatasetLayout):
    description = "transforms_*.json + exposure_*.json + <frame>_<e>.png + *_hdr/ EXR (HDR-NeRF synthetic)"
    writable = True
    detect = staticmethod(detect)
    read = staticmethod(read)
    write = staticmethod(write)
