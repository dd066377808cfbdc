"""nerfstudio layout (docs/datasets.md), read and written: what ns-process-data and instant-ngp write.

    transforms.json   camera_model (OPENCV, OPENCV_FISHEYE or PINHOLE; OPENCV when absent),
                      fl_x, fl_y, cx, cy, w, h (or camera_angle_x / camera_angle_y), distortion
                      k1, k2, k3, k4, p1, p2 - each shared at the top level or per frame;
                      frames[]: file_path (relative, with extension), transform_matrix (OpenGL
                      camera-to-world: x right, y up, z back); optional applied_transform,
                      ply_file_path (points for 3DGS), train_filenames / test_filenames / val_filenames
    images/...        the photos the frames name (any folder)

Photos with lens distortion are resampled onto the pinhole camera of their own fx, fy, cx, cy
(data/undistortion.py, COLMAP's camera models). Frames are ordered by file_path (numeric order);
test_filenames (else val_filenames) are held out, else the frames train_filenames leaves out,
else every 8th frame (i % 8 == 0). nerfstudio stores no exposure times: each photo reads as 1 s,
named in metadata["unknown_exposures"] for the trainer to learn. applied_transform is the
transform ns-process-data applied to COLMAP's world: poses and points are both in its frame
already, so it is kept in metadata only.
"""

import functools
import math
from pathlib import Path, PurePosixPath
from typing import Literal

import numpy as np
import torch

from mono_hdr_plugin.core.cameras import OPENGL_TO_OPENCV, Camera
from mono_hdr_plugin.core.validation import between
from mono_hdr_plugin.data.captures import (
    CapturedScene,
    CapturedView,
    ImageSource,
    Shot,
    bounds_from_cameras,
    bounds_from_points,
)
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import read_image, read_ply_vertices, write_json, write_ply_vertices, write_png
from mono_hdr_plugin.data.layouts.base import DatasetLayout, register_layout
from mono_hdr_plugin.data.layouts.common import (
    UNKNOWN_EXPOSURE,
    camera_from,
    check_finite,
    image_size,
    json_matrix,
    json_name,
    json_number,
    json_object,
    load_json,
    natural_key,
    point_colours_u8,
    read_pose_source,
    write_pose_source,
)
from mono_hdr_plugin.data.undistortion import undistorted_source

Split = Literal["train", "test"]
TRANSFORMS_FILE = "transforms.json"
POINTS_FILE = "sparse_pc.ply"
TEST_EVERY = 8
CAMERA_MODELS = ("OPENCV", "OPENCV_FISHEYE", "PINHOLE")
DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
COLOURS = ("red", "green", "blue")
"""The colour properties of a PLY vertex (uint8), as ns-process-data writes them."""
FIELD_OF_VIEW = between(0, math.pi, low_open=True, high_open=True)


def detect(folder: Path) -> bool:
    return (folder / TRANSFORMS_FILE).is_file()


def clean_path(file_path: str) -> str:
    """A relative file path as one spelling ("./images/a.png" and "images/a.png" are one photo)."""
    return str(PurePosixPath(file_path))


def _intrinsic(frame: dict, shared: dict, key: str, where: str, default=None):
    """A frame's value of `key`, else the shared one, else `default`: a finite number."""
    value = frame.get(key, shared.get(key, default))
    return None if value is None else json_number(value, f"{where}.{key}")


def _pixel_size(frame: dict, shared: dict, where: str, path: Path) -> tuple[int, int]:
    """(w, h) from the file, else the photo's header (instant-ngp may leave them out); the photo must have it."""
    size = image_size(path)
    width, height = (_intrinsic(frame, shared, key, where) for key in ("w", "h"))
    if (width is not None and width != size[0]) or (height is not None and height != size[1]):
        raise DatasetError(
            f"{where}: w, h = {width}, {height} but {path} is {size[0]}x{size[1]}; "
            "fix w and h or export the photo at that size"
        )
    return size


def _focal_lengths(frame: dict, shared: dict, where: str, width: int, height: int) -> tuple[float, float]:
    """fl_x, fl_y, else from camera_angle_x / camera_angle_y (instant-ngp), fl_y defaulting to fl_x."""
    fx = _intrinsic(frame, shared, "fl_x", where)
    if fx is None:
        angle = frame.get("camera_angle_x", shared.get("camera_angle_x"))
        if angle is None:
            raise DatasetError(f"{where}: no focal length; add fl_x (pixels) or camera_angle_x (radians)")
        fx = 0.5 * width / math.tan(0.5 * json_number(angle, f"{where}.camera_angle_x", FIELD_OF_VIEW))
    fy = _intrinsic(frame, shared, "fl_y", where)
    angle_y = frame.get("camera_angle_y", shared.get("camera_angle_y"))
    if fy is None and angle_y is not None:
        fy = 0.5 * height / math.tan(0.5 * json_number(angle_y, f"{where}.camera_angle_y", FIELD_OF_VIEW))
    return fx, fx if fy is None else fy


def colmap_camera_of(model: str, fx: float, fy: float, cx: float, cy: float, distortion: dict, where: str):
    """The COLMAP model name and parameters of a nerfstudio camera (undistortion.py's input).

    nerfstudio's perspective model is OpenCV's (k1, k2, k3 radial; p1, p2 tangential); k3 needs
    COLMAP's FULL_OPENCV. Its r^8 term k4 has no OpenCV model: refused. Fisheye is OpenCV's
    equidistant model with k1..k4.
    """
    k1, k2, k3, k4, p1, p2 = (distortion[key] for key in DISTORTION_KEYS)
    if model == "OPENCV_FISHEYE":
        if p1 or p2:
            raise DatasetError(f"{where}: OPENCV_FISHEYE has no tangential distortion p1, p2; set them to 0")
        return "OPENCV_FISHEYE", [fx, fy, cx, cy, k1, k2, k3, k4]
    if k4:
        raise DatasetError(
            f"{where}: k4 = {k4:g} with camera_model {model} (an r^8 radial term OpenCV's model lacks); "
            "undistort the photos with ns-process-data or COLMAP and set k4 to 0"
        )
    if k3:
        return "FULL_OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2, k3, 0.0, 0.0, 0.0]
    if k1 or k2 or p1 or p2:
        return "OPENCV", [fx, fy, cx, cy, k1, k2, p1, p2]
    return "PINHOLE", [fx, fy, cx, cy]


def _camera_model(frame: dict, shared: dict, where: str) -> str:
    model = frame.get("camera_model", shared.get("camera_model"))
    if model is None:  # instant-ngp writes no camera_model, only is_fisheye
        return "OPENCV_FISHEYE" if frame.get("is_fisheye", shared.get("is_fisheye")) is True else "OPENCV"
    if model not in CAMERA_MODELS:
        raise DatasetError(
            f"{where}: camera_model {model!r} is not supported; use one of {', '.join(CAMERA_MODELS)} "
            "(re-run ns-process-data with --camera-type perspective or fisheye)"
        )
    return model


def _view(folder: Path, frame: dict, shared: dict, where: str, view_id: int, split: Split) -> CapturedView:
    """One frame as a view: its pinhole camera (OpenCV axes) and its photo, undistorted when the lens distorts."""
    file_path = clean_path(json_name(frame["file_path"], f"{where}.file_path"))
    path = folder / file_path
    if not path.is_file():
        raise missing(path, f"restore the photo or remove its frame from {TRANSFORMS_FILE}")
    width, height = _pixel_size(frame, shared, where, path)
    fx, fy = _focal_lengths(frame, shared, where, width, height)
    cx = _intrinsic(frame, shared, "cx", where, width / 2)
    cy = _intrinsic(frame, shared, "cy", where, height / 2)
    distortion = {key: _intrinsic(frame, shared, key, where, 0.0) for key in DISTORTION_KEYS}
    model, params = colmap_camera_of(_camera_model(frame, shared, where), fx, fy, cx, cy, distortion, where)
    c2w_gl = json_matrix(frame["transform_matrix"], f"{where}.transform_matrix", 4, 4)
    camera = camera_from(
        where,
        c2w=torch.from_numpy(c2w_gl).float() @ OPENGL_TO_OPENCV,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        width=width,
        height=height,
    )
    image: ImageSource = functools.partial(read_image, path)
    if model != "PINHOLE":
        image = undistorted_source(image, model, width, height, params)
    return CapturedView(
        view_id=view_id,
        camera=camera,
        split=split,
        shots=[Shot(UNKNOWN_EXPOSURE, image, file_path)],
        name=str(PurePosixPath(file_path).with_suffix("")),
    )


def _listed(transforms: dict, key: str, paths: list[str], transforms_file: Path) -> set[str] | None:
    """The file paths of a train/test/val_filenames list, each one a frame's; None when absent."""
    if key not in transforms:
        return None
    value = transforms[key]
    if not isinstance(value, list):
        raise DatasetError(f"{transforms_file}: {key} must be a list of file paths, got {value!r}")
    listed = {clean_path(json_name(name, f"{transforms_file}: {key}")) for name in value}
    unknown = sorted(listed - set(paths))
    if unknown:
        raise DatasetError(
            f"{transforms_file}: {key} names {', '.join(unknown[:3])}, which no frame has; "
            "fix the list or add the frames"
        )
    return listed


def split_of(transforms: dict, paths: list[str], transforms_file: Path) -> list[Split]:
    """train/test of each frame (in `paths` order): test_filenames (else val_filenames) held out, else
    what train_filenames leaves out, else every 8th frame."""
    test = _listed(transforms, "test_filenames", paths, transforms_file)
    if test is None:
        test = _listed(transforms, "val_filenames", paths, transforms_file)
    train = _listed(transforms, "train_filenames", paths, transforms_file)
    if test is None and train is not None:
        test = set(paths) - train
    if test is None:
        return ["test" if index % TEST_EVERY == 0 else "train" for index in range(len(paths))]
    if test >= set(paths):
        raise DatasetError(f"{transforms_file}: every frame is held out for testing; leave some to train on")
    return ["test" if path in test else "train" for path in paths]


def _points(folder: Path, transforms: dict, transforms_file: Path):
    """The ply_file_path points and colours (in the poses' frame), or None, None."""
    if "ply_file_path" not in transforms:
        return None, None
    path = folder / clean_path(json_name(transforms["ply_file_path"], f"{transforms_file}: ply_file_path"))
    if not path.is_file():
        raise missing(path, f"restore it or remove ply_file_path from {TRANSFORMS_FILE}")
    try:
        vertex = read_ply_vertices(path, "point cloud")
        points = np.stack([vertex[axis] for axis in "xyz"], -1)
    except ValueError as error:
        raise DatasetError(f"{path}: {error}; regenerate it (ns-process-data) or remove ply_file_path") from error
    points = check_finite(points, path, "a point")
    names = vertex.data.dtype.names or ()
    colours = (
        torch.from_numpy(np.stack([vertex[c] for c in COLOURS], -1) / 255.0).float()
        if set(COLOURS) <= set(names)
        else None
    )
    return torch.from_numpy(points).float(), colours


def read(folder: Path) -> CapturedScene:
    """Every frame of a nerfstudio transforms.json, one photo a view, exposures unknown (learned)."""
    transforms_file = folder / TRANSFORMS_FILE
    transforms = json_object(
        load_json(transforms_file, "write it with ns-process-data or instant-ngp's colmap2nerf"), str(transforms_file)
    )
    frames = transforms.get("frames")
    if not isinstance(frames, list) or not frames:
        raise DatasetError(f"{transforms_file}: needs a non-empty 'frames' list")
    checked = []
    for index, frame in enumerate(frames):
        where = f"{transforms_file}: frames[{index}]"
        frame = json_object(frame, where)
        if "file_path" not in frame or "transform_matrix" not in frame:
            raise DatasetError(f"{where} needs 'file_path' and 'transform_matrix'; add them or remove the frame")
        checked.append((clean_path(json_name(frame["file_path"], f"{where}.file_path")), where, frame))
    checked.sort(key=lambda entry: natural_key(entry[0]))
    paths = [path for path, _, _ in checked]
    duplicates = sorted({path for path in paths if paths.count(path) > 1})
    if duplicates:
        raise DatasetError(f"{transforms_file}: {duplicates[0]} is listed by two frames; remove the duplicate frame")
    splits = split_of(transforms, paths, transforms_file)
    views = [
        _view(folder, frame, transforms, where, view_id, split)
        for view_id, ((_, where, frame), split) in enumerate(zip(checked, splits))
    ]
    applied = transforms.get("applied_transform")
    if applied is not None:
        applied = json_matrix(applied, f"{transforms_file}: applied_transform", 3, 4).tolist()
    points, colours = _points(folder, transforms, transforms_file)
    bounds = (
        bounds_from_points(points.numpy()) if points is not None else bounds_from_cameras([v.camera for v in views])
    )
    return CapturedScene(
        name=folder.name,
        views=views,
        bounds_min=bounds[0],
        bounds_max=bounds[1],
        points=points,
        point_colors=colours,
        metadata={
            "source": str(folder),
            "layout": "nerfstudio",
            "unknown_exposures": paths,
            "applied_transform": applied,
            "poses": read_pose_source(folder),
        },
    )


def _intrinsics(camera: Camera) -> dict:
    return {
        "fl_x": camera.fx,
        "fl_y": camera.fy,
        "cx": camera.cx,
        "cy": camera.cy,
        "w": camera.width,
        "h": camera.height,
    }


def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
    """Write images/frame_<n:05d>.png (each view's middle exposure: nerfstudio holds one photo a view and no
    exposure times), sparse_pc.ply of the points, and transforms.json last (pinhole cameras; intrinsics
    shared when every view has the same, else per frame; the scene's split as train/test_filenames)."""
    folder = Path(folder)
    shared = _intrinsics(scene.views[0].camera)
    per_frame = any(_intrinsics(view.camera) != shared for view in scene.views)
    frames: list[dict] = []
    splits: dict[Split, list[str]] = {"train": [], "test": []}
    for index, view in enumerate(scene.views):
        file_path = f"images/frame_{index + 1:05d}.png"
        write_png(folder / file_path, view.shots[len(view.shots) // 2].image(), bits=bits)
        c2w_gl = view.camera.c2w.double() @ OPENGL_TO_OPENCV.double()
        intrinsics = _intrinsics(view.camera) if per_frame else {}
        frames.append({"file_path": file_path, "transform_matrix": c2w_gl.tolist(), **intrinsics})
        splits[view.split].append(file_path)
    extra = {}
    if scene.points is not None:
        vertices = np.zeros(len(scene.points), [(axis, "f4") for axis in "xyz"] + [(c, "u1") for c in COLOURS])
        for axis, values in zip("xyz", scene.points.numpy().T):
            vertices[axis] = values
        for channel, values in zip(COLOURS, point_colours_u8(len(scene.points), scene.point_colors).T):
            vertices[channel] = values
        write_ply_vertices(folder / POINTS_FILE, vertices)
        extra["ply_file_path"] = POINTS_FILE
    header = {"camera_model": "PINHOLE", **({} if per_frame else shared)}
    write_pose_source(scene.metadata, folder)
    write_json(
        folder / TRANSFORMS_FILE,
        {**header, **extra, "train_filenames": splits["train"], "test_filenames": splits["test"], "frames": frames},
    )


@register_layout("nerfstudio")
class NerfstudioLayout(DatasetLayout):
    description = "transforms.json + images (nerfstudio / instant-ngp; distortion removed, exposures learned)"
    writable = True
    detect = staticmethod(detect)
    read = staticmethod(read)
    write = staticmethod(write)
