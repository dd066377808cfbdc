"""HDR-GS COLMAP layout (docs/datasets.md), read and written with pycolmap.

    sparse/0/{cameras,images,points3D}.bin|.txt   COLMAP model, one image entry per view
    images/ (or input_images/)                    <view>_<e>.<ext>, e = 0..4 (t1..t5)
    exr/<view>.exr                                HDR ground truth (synthetic scenes, merged brackets)
    exposures.json (optional)                     {image name: seconds, or null when unknown}
    poses_bounds_exps.npy (real scenes)           column 17 = exposure, row 5 (id - 1) + e
    splits.json (optional)                        {"test": [image names]}: the other views train
    camera_response.json (optional)               the camera's response curve (process-data)
    white_balance.json (optional)                 {image name: "auto", "manual" or null}: EXIF's mode (process-data)
    process_data.json (optional)                  process-data's report: HDR only at bracketed views

Exposure of a photo: exposures.json if present, else the npy row, else the synthetic
t1..t5 = 0.125, 0.5, 2, 8, 32 s that the official code hard-codes. With exposures.json
(`mono-hdr process-data` output) a view is its own image entry plus any `<view>_<e>`
siblings the JSON lists; photos can be at any exposure, and a null exposure (unknown: no EXIF)
reads as 1 s with the view named in the scene's metadata["unknown_exposures"], for the trainer
to learn. Views are ordered by their numeric name (never string order); splits.json names the
test views, without it even views train and odd views test.
"""

import functools
import warnings
from pathlib import Path

import numpy as np
import torch

from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.data.captures import (
    CapturedScene,
    CapturedView,
    ImageFile,
    Shot,
    bounds_from_cameras,
    bounds_from_points,
)
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import read_exr, read_image, utf8_path, write_exr, write_json, write_png
from mono_hdr_plugin.data.layouts.base import DatasetLayout, register_layout
from mono_hdr_plugin.data.layouts.colmap_text import check_text_model
from mono_hdr_plugin.data.layouts.common import (
    UNKNOWN_EXPOSURE,
    camera_from,
    check_exposure,
    check_finite,
    check_one_size,
    image_size,
    json_name,
    json_object,
    load_json,
    natural_key,
    point_colours_u8,
    read_pose_source,
    split_view_exposure,
    write_pose_source,
)

SYNTHETIC_EXPOSURES = (0.125, 0.5, 2.0, 8.0, 32.0)
EXPOSURES_FILE = "exposures.json"
SPLITS_FILE = "splits.json"
RESPONSE_FILE = "camera_response.json"
WHITE_BALANCE_FILE = "white_balance.json"
"""Written by process-data: {image name: "auto", "manual" or null}, EXIF's white balance mode."""
REPORT_FILE = "process_data.json"
"""Written by process-data: its captures have HDR only at the bracketed viewpoints, by design."""
POSES_FILE = "poses_bounds_exps.npy"
MODEL_FOLDER = Path("sparse") / "0"
MAX_EXPOSURES = 5


def detect(folder: Path) -> bool:
    return (folder / MODEL_FOLDER).is_dir()


def _image_folder(folder: Path) -> Path:
    for name in ("images", "input_images"):
        if (folder / name).is_dir():
            return folder / name
    raise missing(folder / "images", "the HDR-GS layout keeps its photos in images/ or input_images/")


def _read_model(folder: Path):
    import pycolmap

    model = folder / MODEL_FOLDER
    if not any((model / f"images.{ext}").is_file() for ext in ("bin", "txt")):
        raise missing(model / "images.bin", "run COLMAP (or mono-hdr process-data) to create sparse/0")
    check_text_model(model)
    try:
        with utf8_path(model) as readable:
            return pycolmap.Reconstruction(str(readable))
    except Exception as error:
        reason = str(error).splitlines()[0][:200] if str(error) else type(error).__name__
        raise DatasetError(f"{model}: cannot read the COLMAP model ({reason}); re-run COLMAP") from error


def _camera(colmap_camera, pose, folder: Path, name: str) -> Camera:
    model = colmap_camera.model.name
    params = list(colmap_camera.params)
    if model == "PINHOLE":
        fx, fy, cx, cy = params
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = params
        fy = fx
    else:
        raise DatasetError(
            f"{folder / MODEL_FOLDER}: image {name} uses camera model {model}; only "
            "PINHOLE and SIMPLE_PINHOLE are supported: undistort the images "
            "(colmap image_undistorter)"
        )
    w2c = np.eye(4)
    w2c[:3] = check_finite(pose.matrix(), folder / MODEL_FOLDER, f"the pose of {name}")
    # COLMAP's pixel (0, 0) covers [0, 1]^2 with its centre at 0.5, the same as Camera's.
    return camera_from(
        f"{folder / MODEL_FOLDER} image {name}",
        c2w=torch.from_numpy(np.linalg.inv(w2c)).float(),
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        width=colmap_camera.width,
        height=colmap_camera.height,
    )


def _cam_from_world(image):
    pose = image.cam_from_world
    return pose() if callable(pose) else pose  # a method since pycolmap 3.12, a property before


class _ExposureSource:
    """Looks up a photo's exposure: exposures.json, else the npy column, else t1..t5."""

    def __init__(self, folder: Path):
        self.json_path = folder / EXPOSURES_FILE
        self.table = (
            json_object(load_json(self.json_path, ""), str(self.json_path)) if self.json_path.exists() else None
        )
        self.npy_path = folder / POSES_FILE
        self.rows = None
        if self.table is None and self.npy_path.is_file():
            try:
                self.rows = np.load(self.npy_path)
            except (ValueError, OSError, EOFError) as error:
                raise DatasetError(f"{self.npy_path}: cannot read the array ({error}); regenerate it") from error
        self.unknown: list[str] = []

    def __call__(self, name: str, image_id: int, e: int) -> float:
        if self.table is not None:
            if name not in self.table:
                raise DatasetError(
                    f"{self.json_path}: no exposure for {name!r}; add it (seconds, or null when unknown)"
                )
            if self.table[name] is None:
                self.unknown.append(name)
                return UNKNOWN_EXPOSURE
            return check_exposure(self.table[name], f"{self.json_path} [{name!r}]")
        if self.rows is not None:
            row = (image_id - 1) * MAX_EXPOSURES + e
            if self.rows.ndim != 2 or self.rows.shape[1] < 18 or not 0 <= row < len(self.rows):
                raise DatasetError(
                    f"{self.npy_path}: no row {row} for {name} (shape {self.rows.shape}); "
                    "the exposures are out of step with the COLMAP images: regenerate it"
                )
            return check_exposure(self.rows[row, 17], f"{self.npy_path} row {row} ({name})")
        if e >= len(SYNTHETIC_EXPOSURES):
            raise DatasetError(f"{name}: exposure index {e} has no default time; write {self.json_path.name}")
        return SYNTHETIC_EXPOSURES[e]


def _view_shots(images: Path, name: str, image_id: int, exposures: _ExposureSource) -> list[Shot]:
    """The entry's own photo and its `<view>_<e>` siblings (those the exposure table knows)."""
    parsed = split_view_exposure(name)
    if parsed is None:
        if exposures.table is None:
            raise DatasetError(
                f"{images / name}: expected <view>_<exposure index>.<ext> (e.g. 0_0.png) "
                f"or an {EXPOSURES_FILE} giving each image's exposure; add one"
            )
        candidates = [(name, 0)]
    else:
        suffix = Path(name).suffix
        candidates = [(f"{parsed[0]}_{e}{suffix}", e) for e in range(MAX_EXPOSURES)]
        if exposures.table is not None:
            candidates = [(n, e) for n, e in candidates if n == name or n in exposures.table]
    shots = []
    for sibling, e in candidates:
        path = images / sibling
        if not path.is_file():
            if sibling == name or exposures.table is not None:
                raise missing(path, f"restore the photo or remove it from sparse/0 and {EXPOSURES_FILE}")
            continue
        shots.append(Shot(exposures(sibling, image_id, e), functools.partial(read_image, path), sibling))
    return sorted(shots, key=lambda shot: shot.exposure)


def _points(model, where: Path):
    """The model's points and colours; points with NaN/Inf coordinates are left out, with a warning."""
    if not model.points3D:
        return None, None
    entries = [point for _, point in sorted(model.points3D.items())]
    points = np.stack([point.xyz for point in entries])
    colours = np.stack([point.color for point in entries]) / 255.0
    finite = np.isfinite(points).all(-1)
    if not finite.all():
        warnings.warn(
            f"{where}: {int((~finite).sum())} of {len(points)} COLMAP points have NaN/Inf coordinates "
            "and are left out of the initialisation; re-run COLMAP to get them back",
            stacklevel=3,
        )
        points, colours = points[finite], colours[finite]
        if not len(points):
            return None, None
    return torch.from_numpy(points).float(), torch.from_numpy(colours).float()


def _response(folder: Path) -> tuple[list | None, str | None]:
    """The response table [256][3] (code value k / 255 -> linear) of camera_response.json, if any, and
    where it came from (its "source")."""
    path = folder / RESPONSE_FILE
    if not path.is_file():
        return None, None
    content = load_json(path, "delete it; process-data writes it again")
    table = np.asarray(content.get("linear_rgb", []), np.float64)
    if table.shape != (256, 3) or not np.isfinite(table).all() or (np.diff(table, axis=0) <= 0).any():
        raise DatasetError(
            f"{path}: linear_rgb must be 256 increasing [r, g, b] rows; delete the file (sRGB is "
            "then assumed) or run process-data again"
        )
    source = content.get("source")
    return table.tolist(), source if isinstance(source, str) else f"of {path.name}"


def _auto_white_balance(folder: Path) -> list[str]:
    """The photos whose camera chose the white balance itself (white_balance.json): the trainer learns
    their gains (core.white_balance)."""
    path = folder / WHITE_BALANCE_FILE
    if not path.is_file():
        return []
    return [name for name, mode in json_object(load_json(path, ""), str(path)).items() if mode == "auto"]


def _test_names(folder: Path, names: list[str]) -> set[str] | None:
    """The image names splits.json holds out for testing; None without the file."""
    path = folder / SPLITS_FILE
    if not path.is_file():
        return None
    splits = load_json(path, 'write {"test": [image names]}')
    test = splits.get("test") if isinstance(splits, dict) else None
    if not isinstance(test, list):
        raise DatasetError(f'{path}: expected {{"test": [image names]}}; fix or delete the file')
    unknown = sorted(set(test) - set(names))
    if unknown:
        raise DatasetError(f"{path}: names images that are not in sparse/0: {', '.join(unknown[:5])}; fix the names")
    if set(test) >= set(names):
        raise DatasetError(f"{path}: holds out every image of sparse/0 for testing; leave some views to train on")
    return set(test)


def _sorted_images(model, folder: Path) -> list:
    """The model's (image id, image) entries in numeric name order, each name checked as JSON-safe text."""
    try:
        entries = sorted(model.images.items(), key=lambda item: natural_key(item[1].name))
    except UnicodeDecodeError as error:
        raise DatasetError(
            f"{folder / MODEL_FOLDER}: an image name is not UTF-8 text ({error.reason}); rename the "
            "images and re-run COLMAP"
        ) from error
    for _, image in entries:
        json_name(image.name, f"{folder / MODEL_FOLDER}: image name")
    if not entries:
        raise DatasetError(f"{folder / MODEL_FOLDER}: the COLMAP model has no images; re-run COLMAP")
    return entries


def _captured_view(
    view_id: int, image, shots: list[Shot], model, folder: Path, test_names: set[str] | None
) -> CapturedView:
    """One COLMAP image entry as a view: its camera, split, photos and HDR ground truth (exr/<view>.exr)."""
    camera = _camera(model.cameras[image.camera_id], _cam_from_world(image), folder, image.name)
    token = Path(image.name).stem.split("_")[0]
    exr = folder / "exr" / f"{token}.exr"
    test = view_id % 2 == 1 if test_names is None else image.name in test_names
    return CapturedView(
        view_id=view_id,
        camera=camera,
        split="test" if test else "train",
        shots=shots,
        name=token,
        hdr=ImageFile(exr, read_exr) if exr.is_file() else None,
    )


def _check_camera_sizes(views: list[CapturedView], width: int, height: int, folder: Path) -> None:
    """Every COLMAP camera must have the size of the photos."""
    for view in views:
        if (view.camera.width, view.camera.height) != (width, height):
            raise DatasetError(
                f"{folder / MODEL_FOLDER}: camera of {view.shots[0].name} is "
                f"{view.camera.width}x{view.camera.height} but the photos are {width}x{height}; "
                "re-run COLMAP on these images or resize them"
            )


def _check_each_photo_once(
    views: list[CapturedView], names: list[str], exposures: _ExposureSource, folder: Path
) -> None:
    """A photo belongs to one view (two COLMAP entries of one view would train and score it twice), and
    every exposures.json entry to a photo of the model (a stray one is a photo the model lost). `names`:
    the COLMAP image name of each view."""
    owner: dict[str, str] = {}
    for name, view in zip(names, views, strict=True):
        for shot in view.shots:
            if shot.name in owner:
                raise DatasetError(
                    f"{folder / MODEL_FOLDER}: images {owner[shot.name]} and {name} both take the photo "
                    f"{shot.name} (a view is its image entry and its <view>_<e> siblings); keep one image "
                    "entry per view"
                )
            owner[shot.name] = name
    if exposures.table is not None:
        stray = sorted(set(exposures.table) - set(owner) - set(names), key=natural_key)
        if stray:
            raise DatasetError(
                f"{exposures.json_path}: entries {stray[:3]} match no photo of {folder / MODEL_FOLDER}; the "
                "exposure file is out of step with the COLMAP model: remove them or re-run process-data"
            )


def read(folder: Path) -> CapturedScene:
    """Every photo of an HDR-GS scene, with the COLMAP points for initialisation."""
    model = _read_model(folder)
    images = _image_folder(folder)
    exposures = _ExposureSource(folder)
    entries = _sorted_images(model, folder)
    test_names = _test_names(folder, [image.name for _, image in entries])
    views, sizes = [], {}
    for view_id, (image_id, image) in enumerate(entries):
        shots = _view_shots(images, image.name, image_id, exposures)
        sizes.update({images / s.name: image_size(images / s.name) for s in shots})
        views.append(_captured_view(view_id, image, shots, model, folder, test_names))
    width, height = check_one_size(sizes, images)
    _check_camera_sizes(views, width, height, folder)
    _check_each_photo_once(views, [image.name for _, image in entries], exposures, folder)
    points, colours = _points(model, folder / MODEL_FOLDER)
    response, response_source = _response(folder)
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
            "layout": "hdr-gs",
            "poses": read_pose_source(folder),
            "unknown_exposures": exposures.unknown,
            "auto_white_balance": _auto_white_balance(folder),
            "camera_response": response,
            "camera_response_source": response_source,
            "partial_hdr_expected": (folder / REPORT_FILE).is_file(),
        },
    )


def _write_model(scene: CapturedScene, model_folder: Path) -> None:
    import pycolmap

    reconstruction = pycolmap.Reconstruction()
    camera = scene.views[0].camera
    reconstruction.add_camera_with_trivial_rig(
        pycolmap.Camera(
            model="PINHOLE",
            width=camera.width,
            height=camera.height,
            camera_id=1,
            params=[camera.fx, camera.fy, camera.cx, camera.cy],
        )
    )
    for index, view in enumerate(scene.views):
        w2c = view.camera.w2c.double().numpy()
        image = pycolmap.Image(name=f"{index:03d}_0.png", camera_id=1, image_id=index + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(w2c[:3, :3]), w2c[:3, 3])
        reconstruction.add_image_with_trivial_frame(image, pose)
    if scene.points is not None:
        for xyz, rgb in zip(scene.points.double().numpy(), point_colours_u8(len(scene.points), scene.point_colors)):
            reconstruction.add_point3D(xyz, pycolmap.Track(), rgb)
    model_folder.mkdir(parents=True, exist_ok=True)
    with utf8_path(model_folder) as writable:
        reconstruction.write(str(writable))


def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
    """Write images/<view:03d>_<e>.png, exr/<view:03d>.exr, sparse/0 and exposures.json.

    Zero-padded view names make even the official string-sorting loader split correctly.
    """
    folder = Path(folder)
    exposures = {}
    for index, view in enumerate(scene.views):
        if view.hdr is not None:
            write_exr(folder / "exr" / f"{index:03d}.exr", view.hdr())
        for e, shot in enumerate(view.shots):
            name = f"{index:03d}_{e}.png"
            write_png(folder / "images" / name, shot.image(), bits=bits)
            exposures[name] = shot.exposure
    write_json(folder / EXPOSURES_FILE, exposures)
    _write_model(scene, folder / MODEL_FOLDER)
    write_pose_source(scene.metadata, folder)


@register_layout("hdr-gs")
class HdrGsLayout(DatasetLayout):
    description = "COLMAP sparse/0 + images/ + exr/ + exposures.json (HDR-GS, Mono-HDR-GS)"
    writable = True
    detect = staticmethod(detect)
    read = staticmethod(read)
    write = staticmethod(write)
