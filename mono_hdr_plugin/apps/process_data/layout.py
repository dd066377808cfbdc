"""Stage 5: the HDR-GS layout written into a scratch folder (images, merged EXRs, the COLMAP model
on a pinhole camera, exposures, splits, the camera response), then renamed into place at once."""

import os
import shutil
from pathlib import Path

import numpy as np
import torch
from rich.console import Console
from rich.progress import track

from mono_hdr_plugin.apps.process_data.brackets import BracketPlan, merge_plan
from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig
from mono_hdr_plugin.apps.process_data.photos import StagedPhoto, photo_pixels
from mono_hdr_plugin.apps.process_data.records import HdrView, PhotoRecord
from mono_hdr_plugin.apps.process_data.report import ProcessReport
from mono_hdr_plugin.apps.process_data.sfm import Reconstruction
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import write_exr, write_json, write_png
from mono_hdr_plugin.data.layouts.hdr_gs import (
    EXPOSURES_FILE,
    MODEL_FOLDER,
    RESPONSE_FILE,
    SPLITS_FILE,
    WHITE_BALANCE_FILE,
)
from mono_hdr_plugin.data.loading import downscale_image
from mono_hdr_plugin.data.photos.brackets import dynamic_range_stops
from mono_hdr_plugin.data.undistortion import PINHOLE_MODELS, pinhole_grid, remap


def write_dataset(
    config: ProcessDataConfig,
    reconstruction: Reconstruction,
    photos: list[PhotoRecord],
    staged: list[StagedPhoto],
    plans: list[BracketPlan],
    hdr_views: list[HdrView],
    response: np.ndarray | None,
    response_source: str | None,
    work: Path,
    dataset: Path,
    console: Console,
) -> ProcessReport:
    """images/, exr/, sparse/0, exposures.json, splits.json and camera_response.json; the report of them."""
    error = reconstruction.model.compute_mean_reprojection_error()
    model, grids = pinhole_model(reconstruction.model, photos, work, console)
    camera_of = {image.name: image.camera_id for image in reconstruction.model.images.values()}
    grid = {photo.name: grids.get(camera_of.get(photo.name, -1)) for photo in photos}
    write_images(config, photos, staged, grid, dataset, console)
    write_hdr_views(config, plans, hdr_views, staged, response, grid, dataset, console)
    test_views = write_metadata(config, model, photos, response, dataset, response_source)
    camera = model.cameras[next(iter(model.cameras))]
    return ProcessReport(
        out=config.out,
        photos=photos,
        camera_model=camera.model.name,
        width=camera.width,
        height=camera.height,
        matcher=reconstruction.matcher,
        mean_reprojection_error=error,
        num_points=model.num_points3D(),
        hdr_views=hdr_views,
        test_views=test_views,
    )


def pinhole_model(model, photos: list[PhotoRecord], work: Path, console: Console):
    """The model of the dataset's views only, on pinhole cameras of one size; for each camera id the
    grid that remaps a photo onto its pinhole camera (None: the photo is the image already).

    Photos of two orientations (portrait and landscape) are placed with a camera each; a backbone
    renders one image size, so every view is cut to the centred window all cameras share (a square
    for a 4:3 phone held both ways) and each camera's principal point moves with its window.
    """
    for image in list(model.images.values()):  # one image per viewpoint: other bracket members leave the model
        if image.has_pose and not next(p.view for p in photos if p.name == image.name):
            model.deregister_frame(image.frame_id)
    distorted = dict(model.cameras.items())
    if any(camera.model.name not in PINHOLE_MODELS for camera in distorted.values()):
        with console.status("undistorting"):
            model = undistort(model, work / "input", work, [p.name for p in photos if p.view])
    offsets = crop_to_shared_window(model)
    grids = {
        camera_id: pinhole_grid(distorted[camera_id], camera, offsets[camera_id])
        for camera_id, camera in model.cameras.items()
    }
    return model, grids


def crop_to_shared_window(model) -> dict[int, tuple[int, int]]:
    """Cut every camera of `model` to the centred window of the smallest width and height among them;
    shift principal points and 2D observations with it. Returns each camera's (left, top) cut."""
    import pycolmap

    width = min(camera.width for camera in model.cameras.values())
    height = min(camera.height for camera in model.cameras.values())
    offsets = {}
    for camera_id, camera in model.cameras.items():
        left, top = (camera.width - width) // 2, (camera.height - height) // 2
        offsets[camera_id] = (left, top)
        if (left, top) == (0, 0) and (camera.width, camera.height) == (width, height):
            continue
        fx, fy, cx, cy = camera.calibration_matrix()[[0, 1, 0, 1], [0, 1, 2, 2]]
        model.cameras[camera_id] = pycolmap.Camera.create_from_model_name(camera_id, "PINHOLE", 1.0, width, height)
        model.cameras[camera_id].params = [fx, fy, cx - left, cy - top]
    for image in model.images.values():
        left, top = offsets[image.camera_id]
        if (left, top) != (0, 0):
            for point in image.points2D:
                point.xy = np.asarray(point.xy) - (left, top)
    return offsets


def write_images(
    config: ProcessDataConfig,
    photos: list[PhotoRecord],
    staged: list[StagedPhoto],
    grid: dict[str, torch.Tensor | None],
    dataset: Path,
    console: Console,
) -> None:
    """images/<view>.png: each view's LDR photo on the pinhole camera, downscaled (16-bit from RAW)."""
    views = [(photo, stage) for photo, stage in zip(photos, staged) if photo.view]
    for photo, stage in track(views, description="writing images", console=console):
        encoded, _ = photo_pixels(stage, config.raw_response)
        pixels = downscale_image(remap(encoded, grid[photo.name]), config.downscale, photo.name)
        write_png(dataset / "images" / photo.name, pixels, bits=16 if stage.raw else 8)


def write_hdr_views(
    config: ProcessDataConfig,
    plans: list[BracketPlan],
    hdr_views: list[HdrView],
    staged: list[StagedPhoto],
    response: np.ndarray | None,
    grid: dict[str, torch.Tensor | None],
    dataset: Path,
    console: Console,
) -> None:
    """exr/<view number>.exr: each bracket set merged, on the pinhole camera, downscaled; its dynamic range."""
    for plan, hdr_view in zip(plans, hdr_views):
        with console.status(f"merging {', '.join(hdr_view.sources)}"):
            hdr = merge_plan(plan, staged, response, config.raw_response, hdr_view.sources)
            hdr = downscale_image(remap(hdr, grid[hdr_view.name]), config.downscale, hdr_view.name)
        hdr_view.dynamic_range_stops = round(dynamic_range_stops(hdr), 2)
        write_exr(dataset / "exr" / f"{hdr_view.name.split('_')[0]}.exr", hdr)


def write_metadata(
    config: ProcessDataConfig,
    model,
    photos: list[PhotoRecord],
    response: np.ndarray | None,
    dataset: Path,
    response_source: str | None = None,
) -> list[str]:
    """sparse/0 (intrinsics scaled to the images), exposures.json, white_balance.json (where EXIF has
    the mode), splits.json, camera_response.json; the test views."""
    if config.downscale > 1:
        scale_intrinsics(model, config.downscale)
    (dataset / MODEL_FOLDER).mkdir(parents=True)
    model.write(dataset / MODEL_FOLDER)
    write_json(dataset / EXPOSURES_FILE, {photo.name: photo.exposure for photo in photos if photo.view})
    if any(photo.white_balance for photo in photos if photo.view):
        write_json(dataset / WHITE_BALANCE_FILE, {photo.name: photo.white_balance for photo in photos if photo.view})
    test_views = choose_test_views(photos, config.test_every)
    write_json(dataset / SPLITS_FILE, {"test": test_views})
    if response is not None:
        write_json(
            dataset / RESPONSE_FILE,
            {
                "source": response_source,
                "code_values": np.linspace(0, 1, len(response)).round(6).tolist(),
                "linear_rgb": response.round(8).tolist(),
            },
        )
    return test_views


def choose_test_views(photos: list[PhotoRecord], every: int) -> list[str]:
    """Every N-th single-exposure view (bracketed views carry the only HDR supervision: they train)."""
    singles = [photo.name for photo in photos if photo.view and photo.bracket is None]
    return [name for position, name in enumerate(singles) if position % every == 0]


def undistort(model, image_dir: Path, work: Path, names: list[str]):
    """The PINHOLE model of a camera model with lens distortion (COLMAP's undistorter)."""
    import pycolmap

    distorted = work / "distorted"
    distorted.mkdir()
    model.write(distorted)
    undistorted = work / "undistorted"
    pycolmap.undistort_images(undistorted, distorted, image_dir, image_names=names, output_type="COLMAP")
    return pycolmap.Reconstruction(undistorted / "sparse")


def scale_intrinsics(model, factor: int) -> None:
    """Intrinsics and 2D observations of images shrunk by `factor` (remainder pixels cropped).

    A block-averaged pixel i covers old pixels [f*i, f*(i+1)), so every image coordinate,
    principal point and focal length is divided by f; cropping the right and bottom
    remainder moves nothing.
    """
    for camera in model.cameras.values():
        params = np.asarray(camera.params, np.float64)
        params[list(camera.focal_length_idxs()) + list(camera.principal_point_idxs())] /= factor
        camera.params = params
        camera.width, camera.height = camera.width // factor, camera.height // factor
    for image in model.images.values():
        for point in image.points2D:
            point.xy = np.asarray(point.xy) / factor


def install(dataset: Path, out: Path, overwrite: bool) -> None:
    """Move the finished dataset to `out` in one rename (the old one goes only after it succeeds)."""
    if out.exists():
        if not overwrite and any(out.iterdir()):
            raise DatasetError(f"{out}: appeared while processing; pass --overwrite or choose another --out")
        old = out.with_name(f".{out.name}.old-{os.getpid()}")
        os.replace(out, old)
        os.replace(dataset, out)
        shutil.rmtree(old)
    else:
        os.replace(dataset, out)
