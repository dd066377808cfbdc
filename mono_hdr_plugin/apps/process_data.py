"""`mono-hdr process-data`: your photos (or a video) -> an HDR-GS dataset the trainer reads.

    photos/IMG_0001.jpg ...   ->   out/images/000_0.png ...     one LDR photo per viewpoint: upright,
    (JPEG, PNG, TIFF, RAW,                                       undistorted, downscaled
     or --video clip.mp4)          out/exr/005.exr ...          linear HDR of every bracketed viewpoint
                                   out/sparse/0/*.bin           COLMAP model of those images (PINHOLE)
                                   out/exposures.json           {image name: seconds, null when unknown}
                                   out/splits.json              the images held out for testing
                                   out/camera_response.json     code value -> linear exposure, when known
                                   out/process_data.json        what happened, which photo became what

Exposure of each photo, first source that has it: EXIF ExposureTime (RAW: LibRaw's metadata;
ISO and aperture folded in when they vary between photos), the --exposure-csv row, the
--exposure value; with none of them anywhere the exposures are unknown (null) and the trainer
learns them. Structure from motion is pycolmap on the CPU over every photo. Photos of one
viewpoint at several exposures (bracket sets, found from capture times and recovered poses)
are merged into one linear HDR image (colour-hdri, photos.brackets); the member as bright as
the other photos is its LDR view. Everything is built in a scratch folder beside --out and renamed into place
at the end, so a failed run never leaves a half-written dataset.
"""

import csv
import json
import math
import os
import shutil
import tempfile
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image, ImageOps, UnidentifiedImageError
from rich.console import Console
from rich.progress import track
from rich.table import Table

from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import write_exr, write_json, write_png
from mono_hdr_plugin.data.layouts.common import check_exposure, natural_key
from mono_hdr_plugin.data.layouts.hdr_gs import (EXPOSURES_FILE, MODEL_FOLDER, REPORT_FILE, RESPONSE_FILE,
                                                 SPLITS_FILE)
from mono_hdr_plugin.data.loading import downscale_image
from mono_hdr_plugin.data.outputs import check_replaceable
from mono_hdr_plugin.data.photos.brackets import (BracketCandidate, BracketTolerances, aligned_members,
                                             brightness_order, detect_brackets, dynamic_range_stops,
                                             estimate_relative_exposures, merge_bracket, recover_response,
                                             response_sample, same_exposure)
from mono_hdr_plugin.data.photos.exif import PhotoExif, read_exif
from mono_hdr_plugin.data.photos.raw import RAW_SUFFIXES, RawResponse, decode, encode, is_raw, read_raw
from mono_hdr_plugin.data.photos.video import extract_frames

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
MIN_IMAGES = 3
EXHAUSTIVE_LIMIT = 80
"""--matcher auto matches every pair up to this many photos, neighbours in file order above."""
WIDE_RANGE_STOPS = 8.0
"""Exposures spanning more stops than this are worth a warning: more than one sensor's range."""
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
RELIABLE_POINTS = 0.5
"""A photo's recovered pose is trusted for bracket detection when it sees this fraction of the
median photo's 3D points."""
FULL_FRAME_WIDTH_MM = 36.0
"""Width of a 35 mm film frame: EXIF FocalLengthIn35mmFilm is relative to it."""
ExposureSource = Literal["exif", "raw", "csv", "flag", "unknown"]


@dataclass
class ProcessDataConfig:
    """Turn photos or a video into a dataset: poses by structure from motion, exposures from EXIF,
    HDR views merged from exposure brackets."""

    out: Path
    """Dataset folder to create (HDR-GS layout); train with `mono-hdr train gs --data OUT`."""
    images: Path | None = None
    """Folder of photos (JPEG, PNG, TIFF or camera RAW) of one scene, all from one camera."""
    video: Path | None = None
    """A video of the scene, instead of --images: frames are taken at --fps, the blurriest dropped."""
    fps: float = 2.0
    """Video: frames per second of clip to keep (each the sharpest of three candidates around its time)."""
    min_sharpness: float = 0.5
    """Video: drop a frame less sharp than this fraction of the median kept frame."""
    exposure: float | None = None
    """Exposure time in seconds for photos whose EXIF has none (and no --exposure-csv row)."""
    exposure_csv: Path | None = None
    """CSV of `file name,seconds` rows for photos whose EXIF has no exposure time."""
    brackets: bool = True
    """Find bracket sets among the photos (one viewpoint, several exposures) and merge each into an
    HDR view; --no-brackets keeps every photo as its own LDR view."""
    bracket: BracketTolerances = field(default_factory=BracketTolerances)
    """How close two photos must be, in time and pose, to count as one viewpoint."""
    raw_response: RawResponse = "srgb"
    """Response curve that turns a RAW photo's linear pixels into its LDR view."""
    test_every: int = 8
    """Hold out every N-th single-exposure view for testing (bracketed views always train)."""
    matcher: Literal["auto", "exhaustive", "sequential"] = "auto"
    """Which photo pairs to match: exhaustive (every pair, small sets), sequential (neighbours in
    file-name order: videos, large sets), or auto (exhaustive up to 80 photos)."""
    downscale: Literal[1, 2, 4] = 1
    """Shrink the training images by this factor (area averaging); intrinsics are scaled to match."""
    camera_model: Literal["SIMPLE_RADIAL", "RADIAL", "OPENCV", "SIMPLE_PINHOLE", "PINHOLE"] = "SIMPLE_RADIAL"
    """COLMAP camera model. Models with lens distortion are estimated, then the images undistorted;
    SIMPLE_PINHOLE/PINHOLE assume distortion-free images (renders, already undistorted photos)."""
    min_registered: float = 0.5
    """Fail when structure from motion places fewer than this fraction of the photos."""
    sequential_overlap: int = 10
    """Sequential matcher: match each photo with this many following photos."""
    overwrite: bool = False
    """Replace --out when it exists already."""
    seed: int = 0
    """Random seed of structure from motion (same photos, same seed: same result)."""
    num_threads: int = -1
    """CPU threads for structure from motion (-1: all)."""


@dataclass
class PhotoRecord:
    """One input photo: where it came from, its exposure, and what became of it."""

    source: str
    """File name in --images (or of the video frame)."""
    name: str
    """File name in OUT/images (a bracket member that is not its set's LDR view is not written)."""
    exposure: float | None
    """Seconds (relative exposure at the reference ISO and aperture when those vary); None: unknown."""
    exposure_source: ExposureSource
    iso: float | None = None
    f_number: float | None = None
    raw: bool = False
    registered: bool = False
    bracket: int | None = None
    """Index of its bracket set in ProcessReport.hdr_views."""
    bracket_exposure: float | None = None
    """Exposure relative to the set's darkest photo, as used by the merge (estimated when unknown)."""
    view: bool = False
    """Whether this photo is an image of the dataset."""


@dataclass
class HdrView:
    """One merged bracket set: the HDR view of the dataset."""

    name: str
    """Its LDR image in OUT/images; the HDR is OUT/exr/<view>.exr."""
    sources: list[str]
    exposures: list[float]
    """Relative exposures of the sources, as merged."""
    exposures_estimated: bool
    """True when the photos had no exposure times and their ratios were measured from the pixels."""
    dynamic_range_stops: float = 0.0
    """log2 of brightest over darkest (1st percentile) luminance of the merged image."""


@dataclass
class VideoRecord:
    """Frames taken from --video."""

    source: str
    fps: float
    candidates: int
    kept: int
    dropped_times: list[float]
    """Seconds into the clip of the candidate frames not kept (less sharp than a neighbour or blurred)."""


@dataclass
class ProcessReport:
    """What process-data did; also written to OUT/process_data.json."""

    out: Path
    photos: list[PhotoRecord]
    camera_model: str
    """Model of the written cameras (PINHOLE after undistortion)."""
    width: int
    height: int
    matcher: str
    mean_reprojection_error: float
    """Pixels, at the resolution structure from motion ran on."""
    num_points: int
    reference_iso: float | None = None
    reference_f_number: float | None = None
    hdr_views: list[HdrView] = field(default_factory=list)
    response: str | None = None
    """Where OUT/camera_response.json came from: recovered from the brackets, or the RAW response."""
    test_views: list[str] = field(default_factory=list)
    ignored: list[str] = field(default_factory=list)
    """Input files not used: JPEG twins of RAW files."""
    video: VideoRecord | None = None
    warnings: list[str] = field(default_factory=list)

    @property
    def registered(self) -> list[PhotoRecord]:
        return [photo for photo in self.photos if photo.registered]

    @property
    def failed(self) -> list[str]:
        """Source file names of the photos left out: not placed by structure from motion nor merged."""
        return [photo.source for photo in self.photos if not photo.registered and photo.bracket is None]

    @property
    def views(self) -> list[PhotoRecord]:
        return [photo for photo in self.photos if photo.view]

    @property
    def exposures_known(self) -> bool:
        return all(photo.exposure is not None for photo in self.photos)

    @property
    def exposure_range(self) -> tuple[float, float] | None:
        """Of the dataset's images (bracket members aside); None when the exposures are unknown."""
        exposures = [photo.exposure for photo in self.views if photo.exposure is not None]
        return (min(exposures), max(exposures)) if exposures else None

    @property
    def exposure_stops(self) -> float | None:
        return None if self.exposure_range is None else math.log2(self.exposure_range[1] / self.exposure_range[0])

    def to_json(self) -> dict:
        return {**asdict(self), "out": str(self.out), "failed": self.failed, "exposure_range": self.exposure_range,
                "exposures_known": self.exposures_known}


# ---------------------------------------------------------------- reading photos


def find_photos(folder: Path) -> tuple[list[Path], list[str]]:
    """The photos in `folder` in natural file-name order (IMG_2 before IMG_10), and the ignored files.

    A JPEG/PNG/TIFF with the same name as a RAW file is the camera's rendering of that RAW: the
    RAW is used and the twin ignored.
    """
    if not folder.is_dir():
        raise missing(folder, "pass --images a folder of JPEG, PNG, TIFF or RAW photos")
    suffixes = PHOTO_SUFFIXES + RAW_SUFFIXES
    found = sorted((path for path in folder.iterdir()
                    if path.is_file() and path.suffix.lower() in suffixes and not path.name.startswith(".")),
                   key=lambda path: natural_key(path.name))
    raw_stems = {path.stem for path in found if is_raw(path)}
    photos = [path for path in found if is_raw(path) or path.stem not in raw_stems]
    ignored = [path.name for path in found if path not in photos]
    if not photos:
        raise DatasetError(f"{folder}: no photos found (looked for {', '.join(suffixes)}); "
                           "point --images at the folder that holds the pictures")
    if len(photos) < MIN_IMAGES:
        raise DatasetError(f"{folder}: only {len(photos)} photo(s); structure from motion needs at least "
                           f"{MIN_IMAGES} overlapping photos, 20-100 around the scene work best")
    return photos, ignored


def load_photo(path: Path) -> tuple[np.ndarray, PhotoExif]:
    """Pixels as float32 [H, W, 3] in [0, 1], turned upright by the EXIF orientation, and the EXIF.

    RAW files give linear pixels (photos.raw); every other format gives its stored code values.
    """
    if is_raw(path):
        return read_raw(path)
    try:
        with Image.open(path) as image:
            image.load()  # decode now: a truncated file fails here with its name
            exif = read_exif(image)
            upright = ImageOps.exif_transpose(image)
            if upright.mode in ("I;16", "I;16B", "I;16L", "I"):
                pixels = np.asarray(upright, np.float32) / 65535.0
                pixels = np.repeat(pixels[..., None], 3, axis=-1)
            else:
                pixels = np.asarray(upright.convert("RGB"), np.float32) / 255.0
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError) as error:
        raise DatasetError(f"{path}: cannot read the photo ({error}); export it again or move it out "
                           "of the folder") from error
    return pixels, exif


@dataclass
class StagedPhoto:
    """A readable photo, copied for structure from motion; its pixels are read again when needed."""

    source: Path
    name: str
    exif: PhotoExif
    raw: bool
    brightness: float
    """Mean code value of the photo."""
    linear: Path | None = None
    """RAW only: its linear pixels, saved once (LibRaw's demosaicing is slow)."""


def photo_pixels(photo: StagedPhoto, raw_response: RawResponse) -> tuple[np.ndarray, np.ndarray | None]:
    """(LDR code values, linear pixels or None): a RAW photo is both; any other photo only the first."""
    if photo.raw:
        linear = np.load(photo.linear)
        return encode(linear, raw_response), linear
    return load_photo(photo.source)[0], None


# ---------------------------------------------------------------- exposures


def read_exposure_csv(path: Path) -> dict[str, float]:
    """`file name,seconds` rows (a header row is allowed) -> {file name: seconds}."""
    if not path.is_file():
        raise missing(path, "pass --exposure-csv a CSV file of `file name,seconds` rows")
    table: dict[str, float] = {}
    with open(path, newline="") as handle:
        for line, row in enumerate(csv.reader(handle), start=1):
            if not row or not "".join(row).strip() or row[0].lstrip().startswith("#"):
                continue
            if len(row) < 2:
                raise DatasetError(f"{path}:{line}: expected `file name,seconds`, got {','.join(row)!r}")
            name, value = row[0].strip(), row[1].strip()
            if line == 1 and _number(value) is None:
                continue  # a header row such as `name,seconds`
            if name in table:
                raise DatasetError(f"{path}:{line}: {name!r} is listed twice; keep one row per photo")
            table[name] = check_exposure(value, f"{path}:{line} ({name})")
    return table


def _number(value) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None


def relative_exposure(time: float, iso: float, f_number: float, reference_iso: float,
                      reference_f_number: float) -> float:
    """Exposure time that collects the same light at the reference ISO and aperture.

    Sensor signal is proportional to t * ISO / N^2, so t * (ISO / ISO_ref) * (N_ref / N)^2.
    """
    return time * (iso / reference_iso) * (reference_f_number / f_number) ** 2


def _most_common(values: list[float | None]) -> float | None:
    """The most frequent known value (the smallest among ties), or None when none is known."""
    known = Counter(value for value in values if value is not None)
    if not known:
        return None
    best = max(known.values())
    return min(value for value, count in known.items() if count == best)


def assign_exposures(sources: list[str], exifs: list[PhotoExif], csv_table: dict[str, float],
                     flag: float | None, csv_path: Path | None = None,
                     raw: list[bool] | None = None) -> tuple[list[tuple[float | None, ExposureSource]], dict]:
    """(seconds or None, source) per photo and the reference ISO/aperture used when those vary.

    EXIF (or RAW metadata) first, then the CSV row, then --exposure. ISO and aperture are folded
    in only when they vary between the photos, so a fixed-setting capture keeps its exact times.
    When no photo has an exposure from any source they are all unknown (the trainer learns them);
    some known and some not is an error, since the unknown ones would have no scale.
    """
    raw = raw or [False] * len(sources)
    unknown = sorted(set(csv_table) - set(sources))
    if unknown:
        raise DatasetError(f"{csv_path}: rows for photos that are not in --images: {', '.join(unknown[:5])}; "
                           "fix the file names in the CSV")
    timed = [exif for exif in exifs if exif.exposure_time is not None]
    isos, f_numbers = {e.iso for e in timed if e.iso}, {e.f_number for e in timed if e.f_number}
    reference = {"iso": _most_common([e.iso for e in timed]) if len(isos) > 1 else None,
                 "f_number": _most_common([e.f_number for e in timed]) if len(f_numbers) > 1 else None}
    # A setting that does not vary is left out (ratio exactly 1); a photo missing a varying one
    # is assumed to have the reference value (exposure_warnings says so).
    iso_reference, f_reference = reference["iso"] or 1.0, reference["f_number"] or 1.0
    exposures, lacking = [], []
    for source, exif, is_raw_photo in zip(sources, exifs, raw):
        if exif.exposure_time is not None:
            iso = (exif.iso or iso_reference) if reference["iso"] else 1.0
            f_number = (exif.f_number or f_reference) if reference["f_number"] else 1.0
            exposures.append((relative_exposure(exif.exposure_time, iso, f_number, iso_reference, f_reference),
                              "raw" if is_raw_photo else "exif"))
        elif source in csv_table:
            exposures.append((csv_table[source], "csv"))
        elif flag is not None:
            exposures.append((check_exposure(flag, "--exposure"), "flag"))
        else:
            exposures.append((None, "unknown"))
            lacking.append(source)
    if lacking and len(lacking) < len(sources):
        raise DatasetError(f"{len(lacking)} photo(s) have no exposure time in their EXIF ({', '.join(lacking[:5])}"
                           f"{', ...' if len(lacking) > 5 else ''}) while the others have one; pass --exposure "
                           "SECONDS (one time for all) or --exposure-csv FILE with `file name,seconds` rows")
    return exposures, reference


def exposure_warnings(photos: list[PhotoRecord], reference: dict) -> list[str]:
    """Notes on the exposure spread of the dataset's views (bracket members aside): unknown, one shared
    exposure, a very wide range, folded ISO/aperture."""
    exposures = [photo.exposure for photo in photos if photo.view and photo.exposure is not None]
    if not exposures:
        return ["no photo has an exposure time (EXIF, --exposure-csv, --exposure): they are written as unknown "
                "and training learns them (--learn-exposure is on for this dataset)"]
    notes = []
    low, high = min(exposures), max(exposures)
    if math.isclose(low, high, rel_tol=1e-3):
        notes.append(f"every photo has the same exposure ({low:.6g} s): the single-exposure setting "
                     "Mono-HDR is made for; HDR is recovered up to one overall scale")
    elif math.log2(high / low) > WIDE_RANGE_STOPS:
        notes.append(f"exposures span {math.log2(high / low):.1f} stops ({low:.6g} s to {high:.6g} s), more "
                     "than one sensor can hold: fine, but check the darkest and brightest photos are usable")
    missing_settings = [p.source for p in photos if (reference["iso"] and p.iso is None and p.exposure_source == "exif")
                        or (reference["f_number"] and p.f_number is None and p.exposure_source == "exif")]
    if missing_settings:
        notes.append(f"ISO or aperture varies but is missing in {', '.join(missing_settings[:5])}; the reference "
                     "value was assumed for them")
    return notes


# ---------------------------------------------------------------- one camera


def check_one_camera(sources: list[str], sizes: list[tuple[int, int]], exifs: list[PhotoExif], folder: Path) -> None:
    """All photos must come from one camera at one size: one set of intrinsics is estimated."""
    by_size = Counter(sizes)
    if len(by_size) > 1:
        listing = ", ".join(f"{count} at {w}x{h} (e.g. {sources[sizes.index((w, h))]})"
                            for (w, h), count in by_size.most_common())
        raise DatasetError(f"{folder}: photos of different sizes after EXIF orientation ({listing}); "
                           "process one camera and one orientation at a time (move the others to another "
                           "folder) or resize them to one size")
    cameras = Counter(exif.camera for exif in exifs if exif.camera)
    if len(cameras) > 1:
        listing = ", ".join(f"{count} from {name!r}" for name, count in cameras.most_common())
        raise DatasetError(f"{folder}: photos from several cameras ({listing}); one set of intrinsics is "
                           "estimated per dataset: process each camera's photos in its own folder")


def _initial_camera_params(model: str, exif: PhotoExif, width: int, height: int) -> str:
    """COLMAP's starting intrinsics: focal from EXIF FocalLengthIn35mmFilm, else COLMAP's guess."""
    if exif.focal_35mm is None:
        return ""
    import pycolmap

    focal = exif.focal_35mm / FULL_FRAME_WIDTH_MM * max(width, height)
    return pycolmap.Camera.create_from_model_name(1, model, focal, width, height).params_to_string()


# ---------------------------------------------------------------- structure from motion


def choose_matcher(matcher: str, count: int) -> str:
    if matcher != "auto":
        return matcher
    return "exhaustive" if count <= EXHAUSTIVE_LIMIT else "sequential"


def run_sfm(config: ProcessDataConfig, image_dir: Path, names: list[str], work: Path, camera_params: str,
            console: Console):
    """Features, matches and incremental mapping; the reconstruction that places the most photos."""
    import pycolmap

    pycolmap.logging.minloglevel = pycolmap.logging.Level.ERROR.value  # keep the console readable
    pycolmap.set_random_seed(config.seed)
    database = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    reader.camera_params = camera_params
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = config.num_threads
    with console.status(f"extracting features from {len(names)} photos"):
        pycolmap.extract_features(database, image_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = config.num_threads
    matcher = choose_matcher(config.matcher, len(names))
    with console.status(f"matching ({matcher})"):
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = config.sequential_overlap
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                      device=pycolmap.Device.cpu)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = config.num_threads
    mapping.random_seed = config.seed
    mapping.min_model_size = MIN_IMAGES
    sparse = work / "sparse"
    sparse.mkdir()
    with console.status("incremental mapping"):
        models = pycolmap.incremental_mapping(database, image_dir, sparse, mapping)
    if not models:
        raise DatasetError(f"{config.images or config.video}: structure from motion placed no photos: the photos do "
                           "not overlap enough or show too little texture. Take more photos with ~70% overlap, avoid "
                           "plain walls and moving objects" + ("" if matcher == "exhaustive" else
                                                               ", or try --matcher exhaustive"))
    largest = max(models.values(), key=lambda model: model.num_reg_images())
    return largest, matcher, len(models)


def check_registered(config: ProcessDataConfig, photos: list[PhotoRecord], models: int,
                     merged: set[str] = frozenset()) -> list[str]:
    """An error when too few photos are used; otherwise the warnings about the ones left out.

    A photo is used when structure from motion placed it or it is merged into a bracket whose
    other photos were placed (`merged`: their source names).
    """
    used = sum(photo.registered or photo.source in merged for photo in photos)
    left_out = [photo.source for photo in photos if not photo.registered and photo.source not in merged]
    needed = max(MIN_IMAGES, math.ceil(config.min_registered * len(photos)))
    split = f" (the photos fell into {models} separate groups; the largest was kept)" if models > 1 else ""
    if used < needed:
        raise DatasetError(f"{config.images or config.video}: structure from motion placed only {used} of "
                           f"{len(photos)} photos (need {needed}, see --min-registered){split}. Not placed: "
                           f"{', '.join(left_out[:10])}{' ...' if len(left_out) > 10 else ''}. Take more "
                           "overlapping photos of textured surfaces, or try --matcher exhaustive and "
                           "--camera-model SIMPLE_RADIAL")
    if left_out:
        return [f"{len(left_out)} photo(s) could not be placed and are left out{split}: {', '.join(left_out)}"]
    return []


# ---------------------------------------------------------------- brackets


def scene_scale(model) -> float:
    """The scene's size in model units: median distance from the cameras to the middle of the points."""
    centres = np.array([image.projection_center() for image in model.images.values() if image.has_pose])
    if model.num_points3D():
        middle = np.median(np.array([point.xyz for point in model.points3D.values()]), axis=0)
    else:
        middle = centres.mean(0)
    distances = np.linalg.norm(centres - middle, axis=1)
    return float(np.median(distances)) if distances.max() > 0 else 1.0


def bracket_candidates(photos: list[PhotoRecord], staged: list[StagedPhoto], model) -> list[BracketCandidate]:
    """What bracket detection needs of each photo; poses seen through fewer than RELIABLE_POINTS of
    the median photo's 3D points are left out (on the studio captures, a bright bracket member seen
    through a third of the median's points was placed 2 % of the scene and 1.6 degrees off)."""
    placed = [image for image in model.images.values() if image.has_pose]
    enough = RELIABLE_POINTS * float(np.median([image.num_points3D for image in placed]))
    poses = {image.name: image for image in placed if image.num_points3D >= enough}
    candidates = []
    for photo, stage in zip(photos, staged):
        image = poses.get(photo.name)
        candidates.append(BracketCandidate(
            name=photo.source, exposure=photo.exposure, timestamp=stage.exif.timestamp,
            auto_bracket=stage.exif.auto_bracket,
            center=None if image is None else np.asarray(image.projection_center()),
            rotation=None if image is None else np.asarray(_cam_from_world(image).rotation.matrix()).T))
    return candidates


def _cam_from_world(image):
    pose = image.cam_from_world
    return pose() if callable(pose) else pose  # a method since pycolmap 3.12, a property before


@dataclass
class BracketPlan:
    """A set to merge: its photos (indices into the photo list) and their relative exposures."""

    members: list[int]
    exposures: list[float]
    estimated: bool
    view: int
    """The member whose LDR photo is the view: placed, and as bright as the capture's single photos."""


def plan_brackets(sets: list[list[int]], photos: list[PhotoRecord], staged: list[StagedPhoto],
                  raw_response: RawResponse, console: Console) -> tuple[list[BracketPlan], list[str]]:
    """Bracket plans of the sets that have a placed photo, and notes on members left out.

    Members whose pixels do not line up with their neighbours' are left out (a placed one becomes
    a single view). Unknown exposure ratios are measured from the pixels. Both look at linear
    values: RAW photos are linear already, other photos go through the sRGB curve (what cameras
    encode with) until the camera's own response is recovered.
    """
    srgb = np.stack([decode(np.linspace(0, 1, 256), "srgb")] * 3, -1)
    in_sets = {i for members in sets if len(members) > 1 for i in members}
    singles = [stage.brightness for i, stage in enumerate(staged) if i not in in_sets]
    typical = float(np.median(singles)) if singles else 0.5  # a set's view looks like the other photos
    plans, notes = [], []
    for members in track([m for m in sets if len(m) > 1], description="checking brackets", console=console):
        placed = [k for k, i in enumerate(members) if photos[i].registered]
        if not placed:
            continue
        names = [photos[i].source for i in members]
        if len({staged[i].raw for i in members}) > 1:
            raise DatasetError(f"{', '.join(names)}: this bracket mixes RAW and JPEG/PNG/TIFF photos; shoot the "
                               "bracket in one format, or pass --no-brackets")
        response = None if staged[members[0]].raw else srgb
        samples = []
        for i in members:
            encoded, linear = photo_pixels(staged[i], raw_response)
            samples.append(response_sample(encoded if linear is None else linear))
        known = photos[members[0]].exposure is not None
        order = (sorted(range(len(members)), key=lambda k: photos[members[k]].exposure) if known
                 else brightness_order(samples))
        start = min(placed, key=lambda k: abs(order.index(k) - len(order) // 2))
        kept = aligned_members(samples, order, start, response)
        dropped = [names[k] for k in range(len(members)) if k not in kept]
        if dropped:
            notes.append(f"{', '.join(dropped)}: do not line up with the other photos of their bracket "
                         f"({', '.join(names[k] for k in kept)}) and are left out of its merge")
        if known:
            exposures = [photos[members[k]].exposure for k in kept]
        else:
            exposures = estimate_relative_exposures([samples[k] for k in kept], response, [names[k] for k in kept])
        if len(kept) < 2 or all(same_exposure(e, exposures[0]) for e in exposures):
            continue  # one viewpoint photographed several times at one exposure: single views
        view = min((k for k in kept if k in placed), key=lambda k: abs(staged[members[k]].brightness - typical))
        plans.append(BracketPlan(members=[members[k] for k in kept], exposures=exposures, estimated=not known,
                                 view=members[view]))
    return plans, notes


def bracket_response(plans: list[BracketPlan], staged: list[StagedPhoto], raw_response: RawResponse,
                     console: Console) -> tuple[np.ndarray | None, str | None]:
    """The camera response [256, 3] of the JPEG brackets (Debevec), or of the RAW photos' chosen curve."""
    coded = [plan for plan in plans if not staged[plan.members[0]].raw]
    if coded:
        samples = []
        for plan in track(coded, description="recovering the camera response", console=console):
            images = [response_sample(photo_pixels(staged[i], raw_response)[0]) for i in plan.members]
            samples.append((images, plan.exposures))
        return recover_response(samples), f"recovered from {len(coded)} bracket set(s) (Debevec & Malik 1997)"
    if any(stage.raw for stage in staged):
        return np.stack([decode(np.linspace(0, 1, 256), raw_response)] * 3, -1), f"{raw_response} (RAW photos)"
    return None, None


# ---------------------------------------------------------------- the command


def process_data(config: ProcessDataConfig, console: Console | None = None) -> ProcessReport:
    """Build the dataset at config.out from config.images or config.video; see the module docstring."""
    console = console or Console(quiet=True)
    check_config(config)
    csv_table = read_exposure_csv(config.exposure_csv) if config.exposure_csv else {}
    config.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{config.out.name}.", dir=config.out.parent) as scratch:
        scratch = Path(scratch)
        work, dataset = scratch / "work", scratch / "dataset"
        (work / "input").mkdir(parents=True)
        video = None
        if config.video is not None:
            kept, dropped = extract_frames(config.video, work / "frames", config.fps,
                                           min_sharpness=config.min_sharpness, console=console)
            video = VideoRecord(source=str(config.video), fps=config.fps, candidates=len(kept) + len(dropped),
                                kept=len(kept), dropped_times=[round(frame.time, 3) for frame in dropped])
            sources, ignored = find_photos(work / "frames")
        else:
            sources, ignored = find_photos(config.images)
        staged, size = stage_photos(sources, work, config.raw_response, console)
        exposures, reference = assign_exposures([p.name for p in sources], [s.exif for s in staged], csv_table,
                                                config.exposure, config.exposure_csv, [s.raw for s in staged])
        photos = [PhotoRecord(source=stage.source.name, name=stage.name, exposure=time, exposure_source=origin,
                              iso=stage.exif.iso, f_number=stage.exif.f_number, raw=stage.raw)
                  for stage, (time, origin) in zip(staged, exposures)]
        params = _initial_camera_params(config.camera_model, staged[0].exif, *size)
        model, matcher, models = run_sfm(config, work / "input", [s.name for s in staged], work, params, console)
        placed = {image.name for image in model.images.values() if image.has_pose}
        for photo in photos:
            photo.registered = photo.name in placed
        plans, bracket_notes = [], []
        if config.brackets and config.video is None:  # a video has no brackets; close frames are not one
            sets = detect_brackets(bracket_candidates(photos, staged, model), scene_scale(model), config.bracket)
            plans, bracket_notes = plan_brackets(sets, photos, staged, config.raw_response, console)
        merged = {i for plan in plans for i in plan.members}
        notes = check_registered(config, photos, models, merged={photos[i].source for i in merged})
        response, response_source = bracket_response(plans, staged, config.raw_response, console)
        hdr_views = mark_views(photos, plans)
        report = write_dataset(config, model, photos, staged, plans, hdr_views, response, work, dataset, matcher,
                               console)
        report.reference_iso, report.reference_f_number = reference["iso"], reference["f_number"]
        report.response, report.ignored, report.video = response_source, ignored, video
        report.warnings = notes + bracket_notes + exposure_warnings(photos, reference)
        write_json(dataset / REPORT_FILE, report.to_json())
        install(dataset, config.out, config.overwrite)
    return report


def check_config(config: ProcessDataConfig) -> None:
    """Flag values that cannot work, before any photo is read."""
    if (config.images is None) == (config.video is None):
        raise DatasetError("pass either --images FOLDER (photos) or --video FILE, not both or neither")
    if config.downscale not in (1, 2, 4):
        raise DatasetError(f"--downscale must be 1, 2 or 4, got {config.downscale}")
    if not 0 < config.min_registered <= 1:
        raise DatasetError(f"--min-registered must be a fraction in (0, 1], got {config.min_registered}")
    if config.test_every < 2:
        raise DatasetError(f"--test-every must be 2 or more (every N-th view is held out), got {config.test_every}")
    if not config.fps > 0:
        raise DatasetError(f"--fps must be a positive number of frames per second, got {config.fps}")
    if not 0 <= config.min_sharpness < 1:
        raise DatasetError(f"--min-sharpness must be a fraction in [0, 1), got {config.min_sharpness}")
    if config.exposure is not None:
        check_exposure(config.exposure, "--exposure")
    if config.out.exists() and not config.out.is_dir():
        raise DatasetError(f"{config.out}: is a file; --out must be a folder to create")
    if config.out.exists() and any(config.out.iterdir()) and not config.overwrite:
        raise DatasetError(f"{config.out}: already exists and is not empty; pass --overwrite to replace it "
                           "or choose another --out")
    if config.images is not None and config.out.resolve() == config.images.resolve():
        raise DatasetError("--out must differ from --images: the photos would be replaced")
    # --out is replaced as a whole: only a dataset process-data wrote, never one holding the inputs.
    check_replaceable(config.out, config.out / REPORT_FILE, [config.images, config.exposure_csv],
                      "process-data --overwrite replaces")


def stage_photos(sources: list[Path], work: Path, raw_response: RawResponse,
                 console: Console) -> tuple[list[StagedPhoto], tuple[int, int]]:
    """8-bit upright copies `<index:03d>_0.png` (the HDR-GS naming) for structure from motion; the size.

    RAW photos are demosaiced once: their linear pixels are kept in work/linear, their SfM copy
    goes through the RAW response.
    """
    staged, sizes, unreadable = [], [], []
    for index, path in enumerate(track(sources, description="reading photos", console=console)):
        try:
            pixels, exif = load_photo(path)
        except DatasetError as error:
            unreadable.append(str(error))
            continue
        stage = StagedPhoto(source=path, name=f"{index:03d}_0.png", exif=exif, raw=is_raw(path), brightness=0.0)
        if stage.raw:
            stage.linear = work / "linear" / f"{index:03d}.npy"
            stage.linear.parent.mkdir(exist_ok=True)
            np.save(stage.linear, pixels)
            pixels = encode(pixels, raw_response)
        stage.brightness = float(pixels.mean())
        write_png(work / "input" / stage.name, pixels)
        staged.append(stage)
        sizes.append((pixels.shape[1], pixels.shape[0]))
    if unreadable:
        raise DatasetError(f"{len(unreadable)} photo(s) cannot be read; fix or remove them:\n  " + "\n  ".join(unreadable))
    check_one_camera([s.source.name for s in staged], sizes, [s.exif for s in staged], sources[0].parent)
    return staged, sizes[0]


def mark_views(photos: list[PhotoRecord], plans: list[BracketPlan]) -> list[HdrView]:
    """Which photos become dataset images (placed singles and each set's view), and the HDR views."""
    members = {i for plan in plans for i in plan.members}
    for index, photo in enumerate(photos):
        photo.view = photo.registered and index not in members
    hdr_views = []
    for number, plan in enumerate(plans):
        darkest = min(plan.exposures)
        for i, exposure in zip(plan.members, plan.exposures):
            photos[i].bracket, photos[i].bracket_exposure = number, exposure / darkest
        photos[plan.view].view = True
        hdr_views.append(HdrView(name=photos[plan.view].name, sources=[photos[i].source for i in plan.members],
                                 exposures=list(plan.exposures), exposures_estimated=plan.estimated))
    return hdr_views


def choose_test_views(photos: list[PhotoRecord], every: int) -> list[str]:
    """Every N-th single-exposure view (bracketed views carry the only HDR supervision: they train)."""
    singles = [photo.name for photo in photos if photo.view and photo.bracket is None]
    return [name for position, name in enumerate(singles) if position % every == 0]


def write_dataset(config: ProcessDataConfig, model, photos: list[PhotoRecord], staged: list[StagedPhoto],
                  plans: list[BracketPlan], hdr_views: list[HdrView], response: np.ndarray | None, work: Path,
                  dataset: Path, matcher: str, console: Console) -> ProcessReport:
    """images/, exr/, sparse/0, exposures.json, splits.json and camera_response.json."""
    error = model.compute_mean_reprojection_error()
    for image in list(model.images.values()):  # one image per viewpoint: other bracket members leave the model
        if image.has_pose and not next(p.view for p in photos if p.name == image.name):
            model.deregister_frame(image.frame_id)
    distorted = model.cameras[next(iter(model.cameras))]
    if distorted.model.name not in PINHOLE_MODELS:
        with console.status("undistorting"):
            model = undistort(model, work / "input", work, [p.name for p in photos if p.view])
    camera = model.cameras[next(iter(model.cameras))]
    grid = pinhole_grid(distorted, camera)
    views = [(photo, stage) for photo, stage in zip(photos, staged) if photo.view]
    for photo, stage in track(views, description="writing images", console=console):
        encoded, _ = photo_pixels(stage, config.raw_response)
        pixels = downscale_image(remap(encoded, grid), config.downscale, photo.name)
        write_png(dataset / "images" / photo.name, pixels, bits=16 if stage.raw else 8)
    for plan, hdr_view in zip(plans, hdr_views):
        with console.status(f"merging {', '.join(hdr_view.sources)}"):
            pixels = [photo_pixels(staged[i], config.raw_response) for i in plan.members]
            images = [linear if linear is not None else encoded for encoded, linear in pixels]
            darkest = min(plan.exposures)
            hdr = merge_bracket(images, [e / darkest for e in plan.exposures],
                                None if staged[plan.members[0]].raw else response, hdr_view.sources)
            hdr = downscale_image(remap(hdr, grid), config.downscale, hdr_view.name)
        hdr_view.dynamic_range_stops = round(dynamic_range_stops(hdr), 2)
        write_exr(dataset / "exr" / f"{hdr_view.name.split('_')[0]}.exr", hdr)
    if config.downscale > 1:
        scale_intrinsics(model, config.downscale)
    (dataset / MODEL_FOLDER).mkdir(parents=True)
    model.write(dataset / MODEL_FOLDER)
    write_json(dataset / EXPOSURES_FILE, {photo.name: photo.exposure for photo, _ in views})
    test_views = choose_test_views(photos, config.test_every)
    write_json(dataset / SPLITS_FILE, {"test": test_views})
    if response is not None:
        write_json(dataset / RESPONSE_FILE, {"code_values": np.linspace(0, 1, len(response)).round(6).tolist(),
                                             "linear_rgb": response.round(8).tolist()})
    camera = model.cameras[next(iter(model.cameras))]
    return ProcessReport(out=config.out, photos=photos, camera_model=camera.model.name, width=camera.width,
                         height=camera.height, matcher=matcher, mean_reprojection_error=error,
                         num_points=model.num_points3D(), hdr_views=hdr_views, test_views=test_views)


# ---------------------------------------------------------------- undistortion and scaling


def undistort(model, image_dir: Path, work: Path, names: list[str]):
    """The PINHOLE model of a camera model with lens distortion (COLMAP's undistorter)."""
    import pycolmap

    distorted = work / "distorted"
    distorted.mkdir()
    model.write(distorted)
    undistorted = work / "undistorted"
    pycolmap.undistort_images(undistorted, distorted, image_dir, image_names=names, output_type="COLMAP")
    return pycolmap.Reconstruction(undistorted / "sparse")


def pinhole_grid(distorted, pinhole) -> torch.Tensor | None:
    """[1, H, W, 2] grid_sample coordinates: where each pixel of the pinhole camera lies in the photo.

    None when the cameras are the same (no distortion). COLMAP's pixel (0, 0) covers [0, 1]^2,
    grid_sample's (align_corners=False) covers [-1, -1 + 2 / W], so x_grid = 2 x / W - 1.
    """
    if distorted.model.name in PINHOLE_MODELS:
        return None
    rows, cols = np.mgrid[0:pinhole.height, 0:pinhole.width].astype(np.float64) + 0.5
    rays = pinhole.cam_from_img(np.stack([cols.ravel(), rows.ravel()], -1))
    pixels = distorted.img_from_cam(np.concatenate([rays, np.ones((len(rays), 1))], -1), check_cheirality=False)
    grid = pixels / np.array([distorted.width, distorted.height]) * 2 - 1
    return torch.from_numpy(grid.reshape(1, pinhole.height, pinhole.width, 2)).float()


def remap(image: np.ndarray, grid: torch.Tensor | None) -> np.ndarray:
    """Bilinear resampling of float [H, W, 3] pixels (LDR or linear HDR) onto the pinhole camera."""
    if grid is None:
        return image
    pixels = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)[None]
    sampled = torch.nn.functional.grid_sample(pixels, grid, mode="bilinear", padding_mode="border",
                                              align_corners=False)
    return sampled[0].permute(1, 2, 0).numpy()


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


# ---------------------------------------------------------------- CLI


def _seconds(value: float | None) -> str:
    return "unknown" if value is None else f"{value:.6g}"


def print_report(report: ProcessReport, console: Console) -> None:
    """Per-photo table, summary, HDR views and warnings."""
    table = Table(title=f"process-data -> {report.out}")
    for column in ("photo", "dataset image", "exposure (s)", "source", "placed", "bracket"):
        table.add_column(column)
    for photo in report.photos:
        bracket = "-" if photo.bracket is None else f"{photo.bracket} ({photo.bracket_exposure:.3g}x)"
        table.add_row(photo.source, photo.name if photo.view else "-", _seconds(photo.exposure),
                      photo.exposure_source, "yes" if photo.registered else "[red]no", bracket)
    console.print(table)
    if report.video is not None:
        video = report.video
        console.print(f"video {video.source}: kept {video.kept} of {video.candidates} candidate frames "
                      f"({video.fps:g} per second, the sharpest of each three, blurred ones dropped)")
    console.print(f"placed {len(report.registered)} / {len(report.photos)} photos ({report.matcher} matching), "
                  f"{report.num_points} points, mean reprojection error {report.mean_reprojection_error:.3f} px")
    exposures = ("exposures unknown (learned in training)" if report.exposure_range is None else
                 f"exposures {report.exposure_range[0]:.6g} s to {report.exposure_range[1]:.6g} s "
                 f"({report.exposure_stops:.1f} stops)")
    console.print(f"camera {report.camera_model} {report.width}x{report.height}; {exposures}")
    if report.reference_iso or report.reference_f_number:
        console.print(f"exposures are relative to ISO {report.reference_iso or '-'}, f/{report.reference_f_number or '-'}")
    singles = len(report.views) - len(report.hdr_views)
    console.print(f"{len(report.views)} views: {len(report.hdr_views)} HDR (merged brackets), {singles} single-exposure "
                  f"LDR; {len(report.test_views)} held out for testing")
    for hdr_view in report.hdr_views:
        how = "ratios measured from the pixels" if hdr_view.exposures_estimated else "exposures from metadata"
        console.print(f"  HDR {hdr_view.name}: {len(hdr_view.sources)} photos ({how}), dynamic range "
                      f"{hdr_view.dynamic_range_stops:.1f} stops")
    if report.response:
        console.print(f"camera response: {report.response}")
    if report.ignored:
        console.print(f"ignored (the RAW file of the same name is used): {', '.join(report.ignored)}")
    for note in report.warnings:
        console.print(f"[yellow]warning:[/yellow] {note}")
    if report.failed:
        console.print(f"[red]left out (not placed):[/red] {', '.join(report.failed)}")
    console.print(f"next: mono-hdr train gs --data {report.out} --out outputs/{report.out.name}")


def process_data_command(config: ProcessDataConfig) -> None:
    """`mono-hdr process-data`: run it and print the report."""
    console = Console()
    print_report(process_data(config, console), console)
