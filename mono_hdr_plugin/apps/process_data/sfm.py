"""Stage 3: camera poses by structure from motion (pycolmap on the CPU over every staged photo)."""

import math
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rich.console import Console

from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig
from mono_hdr_plugin.apps.process_data.photos import MIN_IMAGES
from mono_hdr_plugin.apps.process_data.records import PhotoRecord
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.photos.exif import PhotoExif

EXHAUSTIVE_LIMIT = 80
"""--matcher auto matches every pair up to this many photos, neighbours in file order above."""
FULL_FRAME_WIDTH_MM = 36.0
"""Width of a 35 mm film frame: EXIF FocalLengthIn35mmFilm is relative to it."""


@dataclass
class Reconstruction:
    """What structure from motion found."""

    model: Any
    """The pycolmap.Reconstruction that places the most photos."""
    matcher: str
    """The matcher that ran (auto resolved)."""
    groups: int
    """How many separate reconstructions the photos fell into (the largest is `model`)."""


def initial_camera_params(model: str, exif: PhotoExif, width: int, height: int) -> str:
    """COLMAP's starting intrinsics: focal from EXIF FocalLengthIn35mmFilm, else COLMAP's guess."""
    if exif.focal_35mm is None:
        return ""
    import pycolmap

    focal = exif.focal_35mm / FULL_FRAME_WIDTH_MM * max(width, height)
    return pycolmap.Camera.create_from_model_name(1, model, focal, width, height).params_to_string()


def choose_matcher(matcher: str, count: int) -> str:
    if matcher != "auto":
        return matcher
    return "exhaustive" if count <= EXHAUSTIVE_LIMIT else "sequential"


def run_sfm(
    config: ProcessDataConfig, image_dir: Path, names: list[str], work: Path, camera_params: str, console: Console
) -> Reconstruction:
    """Features, matches and incremental mapping of the photos `names` in `image_dir`."""
    import pycolmap

    pycolmap.logging.minloglevel = pycolmap.logging.Level.ERROR.value  # keep the console readable
    pycolmap.set_random_seed(config.seed)
    database = work / "database.db"
    _extract_features(config, database, image_dir, names, camera_params, console)
    matcher = choose_matcher(config.matcher, len(names))
    _match(config, database, matcher, console)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = config.num_threads
    mapping.random_seed = config.seed
    mapping.min_model_size = MIN_IMAGES
    sparse = work / "sparse"
    sparse.mkdir()
    with console.status("incremental mapping"):
        models = pycolmap.incremental_mapping(database, image_dir, sparse, mapping)
    if not models:
        raise DatasetError(
            f"{config.images or config.video}: structure from motion placed no photos: the photos do "
            "not overlap enough or show too little texture. Take more photos with ~70% overlap, avoid "
            "plain walls and moving objects" + ("" if matcher == "exhaustive" else ", or try --matcher exhaustive")
        )
    largest = max(models.values(), key=lambda model: model.num_reg_images())
    return Reconstruction(model=largest, matcher=matcher, groups=len(models))


def _extract_features(
    config: ProcessDataConfig, database: Path, image_dir: Path, names: list[str], camera_params: str, console: Console
) -> None:
    import pycolmap

    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    reader.camera_params = camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = config.num_threads
    with console.status(f"extracting features from {len(names)} photos"):
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=names,
            camera_mode=pycolmap.CameraMode.SINGLE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )


def _match(config: ProcessDataConfig, database: Path, matcher: str, console: Console) -> None:
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.num_threads
    with console.status(f"matching ({matcher})"):
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = config.sequential_overlap
            pycolmap.match_sequential(
                database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu
            )


def mark_registered(photos: list[PhotoRecord], model) -> None:
    """Set `registered` on the photos structure from motion placed."""
    placed = {image.name for image in model.images.values() if image.has_pose}
    for photo in photos:
        photo.registered = photo.name in placed


def check_registered(
    config: ProcessDataConfig, photos: list[PhotoRecord], models: int, merged: AbstractSet[str] = frozenset()
) -> list[str]:
    """An error when too few photos are used; otherwise the warnings about the ones left out.

    A photo is used when structure from motion placed it or it is merged into a bracket whose
    other photos were placed (`merged`: their source names).
    """
    used = sum(photo.registered or photo.source in merged for photo in photos)
    left_out = [photo.source for photo in photos if not photo.registered and photo.source not in merged]
    needed = max(MIN_IMAGES, math.ceil(config.min_registered * len(photos)))
    split = f" (the photos fell into {models} separate groups; the largest was kept)" if models > 1 else ""
    if used < needed:
        raise DatasetError(
            f"{config.images or config.video}: structure from motion placed only {used} of "
            f"{len(photos)} photos (need {needed}, see --min-registered){split}. Not placed: "
            f"{', '.join(left_out[:10])}{' ...' if len(left_out) > 10 else ''}. Take more "
            "overlapping photos of textured surfaces, or try --matcher exhaustive and "
            "--camera-model SIMPLE_RADIAL"
        )
    if left_out:
        return [f"{len(left_out)} photo(s) could not be placed and are left out{split}: {', '.join(left_out)}"]
    return []
