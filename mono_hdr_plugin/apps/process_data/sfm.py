"""Stage 3: camera poses by structure from motion (pycolmap on the CPU over every staged photo)."""

import math
import time
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig
from mono_hdr_plugin.apps.process_data.photos import MIN_IMAGES, StagedPhoto
from mono_hdr_plugin.apps.process_data.records import PhotoRecord
from mono_hdr_plugin.apps.studio.alignment import similarity
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.photos.exif import PhotoExif

EXHAUSTIVE_LIMIT = 80
"""--matcher auto matches every pair up to this many photos, neighbours in file order above."""
EARTH_RADIUS_M = 6_378_137.0
"""WGS 84 equatorial radius: GPS degrees to metres near the capture (the photos span < a few km)."""
MIN_GPS_PHOTOS = 3
"""A similarity between camera centres and GPS positions needs three points off one line."""
FULL_FRAME_WIDTH_MM = 36.0
"""Width of a 35 mm film frame: EXIF FocalLengthIn35mmFilm is relative to it."""


MAPPERS = ("incremental", "incremental-forward", "global")
"""What --mapper auto tries, in order, until one places every photo (docs/own_photos.md):
COLMAP's incremental mapper with its defaults; the same mapper started from a pair with little
parallax, as a walk or a drive straight ahead gives (COLMAP's first pair must see 16 degrees of
triangulation angle and move less than 95 % along the viewing axis, which no pair of a forward
sequence does); and GLOMAP's global mapper (rotation averaging, then every position at once), which
needs no initial pair."""
FORWARD_START_MIN_ANGLE_DEG = 4.0
"""incremental-forward: the least triangulation angle of the first pair (COLMAP: 16)."""
FORWARD_START_MAX_FORWARD_MOTION = 1.0
"""incremental-forward: any direction of motion may start the model (COLMAP: at most 0.95 along the
viewing axis)."""


@dataclass
class MapperAttempt:
    """One mapper run: what it placed and how well."""

    mapper: str
    placed: int
    mean_reprojection_error: float | None
    """Pixels; None when the mapper placed no photos."""
    seconds: float


@dataclass
class Reconstruction:
    """What structure from motion found."""

    model: Any
    """The pycolmap.Reconstruction that places the most photos."""
    matcher: str
    """The matcher that ran (auto resolved)."""
    groups: int
    """How many separate reconstructions the photos fell into (the largest is `model`)."""
    mapper: str = "incremental"
    """The mapper whose model was kept."""
    attempts: list[MapperAttempt] = field(default_factory=list)
    """Every mapper that ran, in order (--mapper auto stops at the first that places every photo)."""


def initial_camera_params(model: str, exif: PhotoExif, width: int, height: int) -> str:
    """COLMAP's starting intrinsics: focal from EXIF FocalLengthIn35mmFilm, else COLMAP's guess."""
    if exif.focal_35mm is None:
        return ""
    import pycolmap

    focal = exif.focal_35mm / FULL_FRAME_WIDTH_MM * max(width, height)
    return pycolmap.Camera.create_from_model_name(1, model, focal, width, height).params_to_string()


@dataclass
class CameraGroup:
    """Photos that share one camera in structure from motion: one size and orientation."""

    names: list[str]
    """Staged file names (work/input)."""
    params: str
    """Starting intrinsics (COLMAP's parameter string; empty: COLMAP's guess)."""


def camera_groups(model: str, staged: list[StagedPhoto], sizes: list[tuple[int, int]]) -> list[CameraGroup]:
    """One camera per photo size, in order of first appearance: a phone held upright and sideways
    gives portrait and landscape photos whose intrinsics are the same lens turned, but whose
    principal point and lens distortion COLMAP describes in each orientation's own pixels."""
    groups: dict[tuple[int, int], CameraGroup] = {}
    for photo, size in zip(staged, sizes):
        if size not in groups:
            groups[size] = CameraGroup([], initial_camera_params(model, photo.exif, *size))
        groups[size].names.append(photo.name)
    return list(groups.values())


def choose_matcher(matcher: str, count: int) -> str:
    if matcher != "auto":
        return matcher
    return "exhaustive" if count <= EXHAUSTIVE_LIMIT else "sequential"


def choose_mappers(mapper: str) -> tuple[str, ...]:
    """The mappers to try in order: all of MAPPERS for auto, else the one named."""
    return MAPPERS if mapper == "auto" else (mapper,)


def best_attempt(attempts: list[MapperAttempt]) -> int | None:
    """Index of the attempt that placed the most photos (the lower reprojection error breaks a tie,
    then the earlier attempt); None when none placed any."""
    placed = [i for i, attempt in enumerate(attempts) if attempt.placed > 0]
    if not placed:
        return None
    return min(placed, key=lambda i: (-attempts[i].placed, attempts[i].mean_reprojection_error, i))


def run_sfm(
    config: ProcessDataConfig, image_dir: Path, cameras: list[CameraGroup], work: Path, console: Console
) -> Reconstruction:
    """Features, matches and mapping of the photos of `cameras` in `image_dir`: the mappers of
    --mapper in order, keeping the model that places the most photos."""
    import pycolmap

    pycolmap.logging.minloglevel = pycolmap.logging.Level.ERROR.value  # keep the console readable
    pycolmap.set_random_seed(config.seed)
    database = work / "database.db"
    names = [name for camera in cameras for name in camera.names]
    for camera in cameras:  # one extraction per camera: COLMAP's SINGLE mode gives each call one camera
        _extract_features(config, database, image_dir, camera.names, camera.params, console)
    matcher = choose_matcher(config.matcher, len(names))
    _match(config, database, matcher, console)
    attempts: list[MapperAttempt] = []
    results: list[tuple[Any, int]] = []
    for mapper in choose_mappers(config.mapper):
        started = time.perf_counter()
        with console.status(f"mapping ({mapper})"):
            models = _map(config, mapper, database, image_dir, work / "sparse" / mapper)
        largest = max(models.values(), key=lambda model: model.num_reg_images()) if models else None
        attempts.append(
            MapperAttempt(
                mapper=mapper,
                placed=largest.num_reg_images() if largest else 0,
                mean_reprojection_error=largest.compute_mean_reprojection_error() if largest else None,
                seconds=round(time.perf_counter() - started, 2),
            )
        )
        results.append((largest, len(models)))
        if attempts[-1].placed == len(names):
            break
    best = best_attempt(attempts)
    if best is None:
        raise DatasetError(
            f"{config.images or config.video}: structure from motion placed no photos ({_tried(attempts, matcher)}): "
            "the photos do not overlap enough or show too little texture. Take more photos with ~70% overlap, "
            "avoid plain walls and moving objects" + _advice(config, matcher)
        )
    model, groups = results[best]
    return Reconstruction(model=model, matcher=matcher, groups=groups, mapper=attempts[best].mapper, attempts=attempts)


def _map(config: ProcessDataConfig, mapper: str, database: Path, image_dir: Path, sparse: Path) -> dict:
    import pycolmap

    sparse.mkdir(parents=True)
    if mapper == "global":
        options = pycolmap.GlobalPipelineOptions()
        options.num_threads = config.num_threads
        options.random_seed = config.seed
        options.min_model_size = MIN_IMAGES
        return pycolmap.global_mapping(database, image_dir, sparse, options)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = config.num_threads
    mapping.random_seed = config.seed
    mapping.min_model_size = MIN_IMAGES
    if mapper == "incremental-forward":
        mapping.mapper.init_min_tri_angle = FORWARD_START_MIN_ANGLE_DEG
        mapping.mapper.init_max_forward_motion = FORWARD_START_MAX_FORWARD_MOTION
    return pycolmap.incremental_mapping(database, image_dir, sparse, mapping)


def _tried(attempts: list[MapperAttempt], matcher: str) -> str:
    runs = ", ".join(f"{attempt.mapper} placed {attempt.placed}" for attempt in attempts)
    return f"{matcher} matching; {runs}"


def _advice(config: ProcessDataConfig, matcher: str) -> str:
    """What is left to try, given what ran: only settings other than the ones used."""
    options = []
    if matcher != "exhaustive":
        options.append("--matcher exhaustive")
    if config.mapper != "auto":
        options.append("--mapper auto (tries every mapper)")
    if config.camera_model in ("SIMPLE_PINHOLE", "PINHOLE"):
        options.append("--camera-model SIMPLE_RADIAL (photos through a real lens)")
    return f", or try {' and '.join(options)}" if options else ""


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
    config: ProcessDataConfig,
    photos: list[PhotoRecord],
    reconstruction: Reconstruction,
    merged: AbstractSet[str] = frozenset(),
) -> list[str]:
    """An error when too few photos are used; otherwise the warnings about the ones left out.

    A photo is used when structure from motion placed it or it is merged into a bracket whose
    other photos were placed (`merged`: their source names).
    """
    models, matcher, attempts = reconstruction.groups, reconstruction.matcher, reconstruction.attempts
    used = sum(photo.registered or photo.source in merged for photo in photos)
    left_out = [photo.source for photo in photos if not photo.registered and photo.source not in merged]
    needed = max(MIN_IMAGES, math.ceil(config.min_registered * len(photos)))
    split = f" (the photos fell into {models} separate groups; the largest was kept)" if models > 1 else ""
    if used < needed:
        raise DatasetError(
            f"{config.images or config.video}: structure from motion placed only {used} of "
            f"{len(photos)} photos (need {needed}, see --min-registered){split}. Not placed: "
            f"{', '.join(left_out[:10])}{' ...' if len(left_out) > 10 else ''}; tried: "
            f"{_tried(attempts, matcher)}. Take more overlapping photos of textured surfaces"
            f"{_advice(config, matcher)}"
        )
    if left_out:
        return [f"{len(left_out)} photo(s) could not be placed and are left out{split}: {', '.join(left_out)}"]
    return []


def gps_metres(positions: np.ndarray) -> np.ndarray:
    """(latitude, longitude, altitude) rows [N, 3] -> local east, north, up metres around their mean
    (equirectangular: exact to millimetres over the few hundred metres a capture spans)."""
    latitude, longitude, altitude = positions.T
    mean_latitude = np.radians(latitude.mean())
    east = np.radians(longitude - longitude.mean()) * EARTH_RADIUS_M * np.cos(mean_latitude)
    north = np.radians(latitude - latitude.mean()) * EARTH_RADIUS_M
    return np.stack([east, north, altitude - altitude.mean()], -1)


def gps_rms_metres(model, staged: list[StagedPhoto]) -> float | None:
    """RMS distance in metres between the placed photos' camera centres and their GPS positions, after
    the similarity that fits the first onto the second; None when fewer than MIN_GPS_PHOTOS placed
    photos carry GPS or they do not span a plane's worth of directions (a photo taken from one spot)."""
    by_name = {photo.name: photo.exif.gps for photo in staged}
    pairs = [
        (image.projection_center(), by_name[image.name])
        for image in model.images.values()
        if image.has_pose and by_name.get(image.name) is not None
    ]
    if len(pairs) < MIN_GPS_PHOTOS:
        return None
    centres = np.array([centre for centre, _ in pairs], np.float64)
    gps = gps_metres(np.array([position for _, position in pairs], np.float64))
    if np.linalg.norm(gps - gps.mean(0), axis=1).max() < 1e-3 or np.ptp(centres, 0).max() == 0:
        return None
    scale, rotation, translation = similarity(centres, gps)
    residual = scale * centres @ rotation.T + translation - gps
    return float(np.sqrt((residual**2).sum(1).mean()))
