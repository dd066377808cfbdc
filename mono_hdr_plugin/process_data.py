"""`mono-hdr process-data`: a folder of your own photos -> an HDR-GS dataset the trainer reads.

    photos/IMG_0001.jpg ...   ->   out/images/000_0.png ...     oriented (EXIF), undistorted, downscaled
                                   out/sparse/0/*.bin            COLMAP model (PINHOLE/SIMPLE_PINHOLE)
                                   out/exposures.json            {image name: seconds}
                                   out/process_data.json         what happened, and original file names

Exposure of each photo, first source that has it: EXIF ExposureTime (with ISO and aperture
folded in when they vary between photos), the --exposure-csv row, the --exposure value.
Structure from motion is pycolmap on the CPU: SIFT features, exhaustive or sequential
matching, incremental mapping. Everything is built in a scratch folder beside --out and
renamed into place at the end, so a failed run never leaves a half-written dataset.
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
from PIL import Image, ImageOps, UnidentifiedImageError
from rich.console import Console
from rich.progress import track
from rich.table import Table

from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.io import read_image, write_png
from mono_hdr_plugin.data.io import write_json
from mono_hdr_plugin.data.layouts.common import check_exposure, natural_key
from mono_hdr_plugin.data.layouts.hdr_gs import EXPOSURES_FILE, MODEL_FOLDER
from mono_hdr_plugin.data.loading import downscale_image
from mono_hdr_plugin.outputs import check_replaceable

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
MIN_IMAGES = 3
EXHAUSTIVE_LIMIT = 80
"""--matcher auto matches every pair up to this many photos, neighbours in file order above."""
WIDE_RANGE_STOPS = 8.0
"""Exposures spanning more stops than this are worth a warning: more than one sensor's range."""
PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
REPORT_FILE = "process_data.json"
FULL_FRAME_WIDTH_MM = 36.0
"""Width of a 35 mm film frame: EXIF FocalLengthIn35mmFilm is relative to it."""

# EXIF tag numbers (EXIF 2.32). Orientation is applied by ImageOps.exif_transpose.
EXIF_IFD = 0x8769
TAG_MAKE, TAG_MODEL = 0x010F, 0x0110
TAG_EXPOSURE_TIME, TAG_F_NUMBER, TAG_ISO, TAG_FOCAL_35MM = 0x829A, 0x829D, 0x8827, 0xA405


@dataclass
class ProcessDataConfig:
    """Turn a folder of photos into a dataset: poses by structure from motion, exposures from EXIF."""

    images: Path
    """Folder of photos (JPEG, PNG or TIFF) of one scene, all from one camera."""
    out: Path
    """Dataset folder to create (HDR-GS layout); train with `mono-hdr train gs --data OUT`."""
    exposure: float | None = None
    """Exposure time in seconds for photos whose EXIF has none (and no --exposure-csv row)."""
    exposure_csv: Path | None = None
    """CSV of `file name,seconds` rows for photos whose EXIF has no exposure time."""
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
    """One input photo: where it came from, its exposure, and whether SfM placed it."""

    source: str
    """File name in --images."""
    name: str
    """File name in OUT/images."""
    exposure: float
    """Seconds (relative exposure at the reference ISO and aperture when those vary)."""
    exposure_source: Literal["exif", "csv", "flag"]
    iso: float | None = None
    f_number: float | None = None
    registered: bool = False


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
    warnings: list[str] = field(default_factory=list)

    @property
    def registered(self) -> list[PhotoRecord]:
        return [photo for photo in self.photos if photo.registered]

    @property
    def failed(self) -> list[str]:
        """Source file names of the photos structure from motion could not place."""
        return [photo.source for photo in self.photos if not photo.registered]

    @property
    def exposure_range(self) -> tuple[float, float]:
        exposures = [photo.exposure for photo in self.registered]
        return min(exposures), max(exposures)

    @property
    def exposure_stops(self) -> float:
        low, high = self.exposure_range
        return math.log2(high / low)

    def to_json(self) -> dict:
        return {**asdict(self), "out": str(self.out), "failed": self.failed,
                "exposure_range": list(self.exposure_range)}


@dataclass
class PhotoExif:
    """The EXIF fields process-data uses (None when absent)."""

    exposure_time: float | None = None
    f_number: float | None = None
    iso: float | None = None
    focal_35mm: float | None = None
    camera: str | None = None


# ---------------------------------------------------------------- reading photos


def find_photos(folder: Path) -> list[Path]:
    """The photos in `folder`, in natural file-name order (IMG_2 before IMG_10)."""
    if not folder.is_dir():
        raise missing(folder, "pass --images a folder of JPEG, PNG or TIFF photos")
    photos = sorted((path for path in folder.iterdir()
                     if path.is_file() and path.suffix.lower() in PHOTO_SUFFIXES and not path.name.startswith(".")),
                    key=lambda path: natural_key(path.name))
    if not photos:
        raise DatasetError(f"{folder}: no photos found (looked for {', '.join(PHOTO_SUFFIXES)}); "
                           "point --images at the folder that holds the pictures")
    if len(photos) < MIN_IMAGES:
        raise DatasetError(f"{folder}: only {len(photos)} photo(s); structure from motion needs at least "
                           f"{MIN_IMAGES} overlapping photos, 20-100 around the scene work best")
    return photos


def _number(value) -> float | None:
    """An EXIF number (rational, int, or a tuple of them) as a float; None when unusable."""
    if isinstance(value, (tuple, list)):
        value = value[0] if value else None
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def read_exif(image: Image.Image) -> PhotoExif:
    """The exposure, aperture, ISO, 35 mm focal length and camera name of an opened image."""
    exif = image.getexif()
    details = exif.get_ifd(EXIF_IFD)

    def tag(number):
        return details.get(number, exif.get(number))  # TIFFs may keep them in the main IFD

    camera = " ".join(str(exif.get(t, "")).strip("\x00 ") for t in (TAG_MAKE, TAG_MODEL)).strip()
    return PhotoExif(exposure_time=_number(tag(TAG_EXPOSURE_TIME)), f_number=_number(tag(TAG_F_NUMBER)),
                     iso=_number(tag(TAG_ISO)), focal_35mm=_number(tag(TAG_FOCAL_35MM)), camera=camera or None)


def load_photo(path: Path) -> tuple[np.ndarray, PhotoExif]:
    """Pixels as float32 [H, W, 3] in [0, 1], turned upright by the EXIF orientation, and the EXIF."""
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
                     flag: float | None, csv_path: Path | None = None) -> tuple[list[tuple[float, str]], dict]:
    """(seconds, source) per photo and the reference ISO/aperture used when those vary.

    EXIF first, then the CSV row, then --exposure. ISO and aperture are folded in only when
    they vary between the EXIF photos, so a fixed-setting capture keeps its exact EXIF times.
    """
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
    for source, exif in zip(sources, exifs):
        if exif.exposure_time is not None:
            iso = (exif.iso or iso_reference) if reference["iso"] else 1.0
            f_number = (exif.f_number or f_reference) if reference["f_number"] else 1.0
            exposures.append((relative_exposure(exif.exposure_time, iso, f_number, iso_reference, f_reference), "exif"))
        elif source in csv_table:
            exposures.append((csv_table[source], "csv"))
        elif flag is not None:
            exposures.append((check_exposure(flag, "--exposure"), "flag"))
        else:
            lacking.append(source)
    if lacking:
        raise DatasetError(f"{len(lacking)} photo(s) have no exposure time in their EXIF ({', '.join(lacking[:5])}"
                           f"{', ...' if len(lacking) > 5 else ''}); pass --exposure SECONDS (one time for all) "
                           "or --exposure-csv FILE with `file name,seconds` rows")
    return exposures, reference


def exposure_warnings(photos: list[PhotoRecord], reference: dict) -> list[str]:
    """Notes on the exposure spread: one shared exposure, a very wide range, folded ISO/aperture."""
    notes = []
    exposures = [photo.exposure for photo in photos if photo.registered]
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
        raise DatasetError(f"{config.images}: structure from motion placed no photos: the photos do not overlap "
                           "enough or show too little texture. Take more photos with ~70% overlap, avoid plain "
                           "walls and moving objects" + ("" if matcher == "exhaustive" else
                                                         ", or try --matcher exhaustive"))
    largest = max(models.values(), key=lambda model: model.num_reg_images())
    return largest, matcher, len(models)


def check_registered(config: ProcessDataConfig, photos: list[PhotoRecord], models: int) -> list[str]:
    """An error when too few photos were placed; otherwise the warnings about the ones left out."""
    placed = sum(photo.registered for photo in photos)
    failed = [photo.source for photo in photos if not photo.registered]
    needed = max(MIN_IMAGES, math.ceil(config.min_registered * len(photos)))
    split = f" (the photos fell into {models} separate groups; the largest was kept)" if models > 1 else ""
    if placed < needed:
        raise DatasetError(f"{config.images}: structure from motion placed only {placed} of {len(photos)} photos "
                           f"(need {needed}, see --min-registered){split}. Not placed: {', '.join(failed[:10])}"
                           f"{' ...' if len(failed) > 10 else ''}. Take more overlapping photos of textured "
                           "surfaces, or try --matcher exhaustive and --camera-model SIMPLE_RADIAL")
    if failed:
        return [f"{len(failed)} photo(s) could not be placed and are left out{split}: {', '.join(failed)}"]
    return []


def undistort(model, image_dir: Path, work: Path):
    """A PINHOLE model and undistorted images for a camera model with lens distortion."""
    import pycolmap

    distorted = work / "distorted"
    distorted.mkdir()
    model.write(distorted)
    undistorted = work / "undistorted"
    pycolmap.undistort_images(undistorted, distorted, image_dir, output_type="COLMAP")
    return pycolmap.Reconstruction(undistorted / "sparse"), undistorted / "images"


# ---------------------------------------------------------------- the command


def process_data(config: ProcessDataConfig, console: Console | None = None) -> ProcessReport:
    """Build the dataset at config.out from the photos in config.images; see the module docstring."""
    console = console or Console(quiet=True)
    check_config(config)
    sources = find_photos(config.images)
    csv_table = read_exposure_csv(config.exposure_csv) if config.exposure_csv else {}
    config.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{config.out.name}.", dir=config.out.parent) as scratch:
        scratch = Path(scratch)
        work, dataset = scratch / "work", scratch / "dataset"
        (work / "input").mkdir(parents=True)
        names, exifs, size = stage_photos(sources, work / "input", console)
        exposures, reference = assign_exposures([p.name for p in sources], exifs, csv_table, config.exposure,
                                                config.exposure_csv)
        photos = [PhotoRecord(source=path.name, name=name, exposure=time, exposure_source=origin,
                              iso=exif.iso, f_number=exif.f_number)
                  for path, name, exif, (time, origin) in zip(sources, names, exifs, exposures)]
        params = _initial_camera_params(config.camera_model, exifs[0], *size)
        model, matcher, models = run_sfm(config, work / "input", names, work, params, console)
        placed = {image.name for image in model.images.values()}
        for photo in photos:
            photo.registered = photo.name in placed
        notes = check_registered(config, photos, models)
        report = write_dataset(config, model, photos, work, dataset, matcher, console)
        report.reference_iso, report.reference_f_number = reference["iso"], reference["f_number"]
        report.warnings = notes + exposure_warnings(photos, reference)
        write_json(dataset / REPORT_FILE, report.to_json())
        install(dataset, config.out, config.overwrite)
    return report


def check_config(config: ProcessDataConfig) -> None:
    """Flag values that cannot work, before any photo is read."""
    if config.downscale not in (1, 2, 4):
        raise DatasetError(f"--downscale must be 1, 2 or 4, got {config.downscale}")
    if not 0 < config.min_registered <= 1:
        raise DatasetError(f"--min-registered must be a fraction in (0, 1], got {config.min_registered}")
    if config.exposure is not None:
        check_exposure(config.exposure, "--exposure")
    if config.out.exists() and not config.out.is_dir():
        raise DatasetError(f"{config.out}: is a file; --out must be a folder to create")
    if config.out.exists() and any(config.out.iterdir()) and not config.overwrite:
        raise DatasetError(f"{config.out}: already exists and is not empty; pass --overwrite to replace it "
                           "or choose another --out")
    if config.out.resolve() == config.images.resolve():
        raise DatasetError("--out must differ from --images: the photos would be replaced")
    # --out is replaced as a whole: only a dataset process-data wrote, never one holding the inputs.
    check_replaceable(config.out, config.out / REPORT_FILE, [config.images, config.exposure_csv],
                      "process-data --overwrite replaces")


def stage_photos(sources: list[Path], folder: Path, console: Console):
    """Upright PNG copies named `<index:03d>_0.png` (the HDR-GS naming), their EXIF and the image size."""
    names, exifs, sizes, unreadable = [], [], [], []
    for index, path in enumerate(track(sources, description="reading photos", console=console)):
        try:
            pixels, exif = load_photo(path)
        except DatasetError as error:
            unreadable.append(str(error))
            continue
        name = f"{index:03d}_0.png"
        write_png(folder / name, pixels)
        names.append(name)
        exifs.append(exif)
        sizes.append((pixels.shape[1], pixels.shape[0]))
    if unreadable:
        raise DatasetError(f"{len(unreadable)} photo(s) cannot be read; fix or remove them:\n  " + "\n  ".join(unreadable))
    check_one_camera([p.name for p in sources], sizes, exifs, sources[0].parent)
    return names, exifs, sizes[0]


def write_dataset(config: ProcessDataConfig, model, photos: list[PhotoRecord], work: Path, dataset: Path,
                  matcher: str, console: Console) -> ProcessReport:
    """images/, sparse/0 and exposures.json of the placed photos, undistorted and downscaled."""
    image_dir = work / "input"
    error = model.compute_mean_reprojection_error()
    if model.cameras[next(iter(model.cameras))].model.name not in PINHOLE_MODELS:
        with console.status("undistorting"):
            model, image_dir = undistort(model, image_dir, work)
    placed = [photo for photo in photos if photo.registered]
    for photo in track(placed, description="writing images", console=console):
        pixels = downscale_image(read_image(image_dir / photo.name), config.downscale, photo.name)
        write_png(dataset / "images" / photo.name, pixels)
    if config.downscale > 1:
        scale_intrinsics(model, config.downscale)
    (dataset / MODEL_FOLDER).mkdir(parents=True)
    model.write(dataset / MODEL_FOLDER)
    write_json(dataset / EXPOSURES_FILE, {photo.name: photo.exposure for photo in placed})
    camera = model.cameras[next(iter(model.cameras))]
    return ProcessReport(out=config.out, photos=photos, camera_model=camera.model.name, width=camera.width,
                         height=camera.height, matcher=matcher, mean_reprojection_error=error,
                         num_points=model.num_points3D())


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


def print_report(report: ProcessReport, console: Console) -> None:
    """Per-photo table, summary and warnings."""
    table = Table(title=f"process-data -> {report.out}")
    for column in ("photo", "dataset name", "exposure (s)", "source", "placed"):
        table.add_column(column)
    for photo in report.photos:
        table.add_row(photo.source, photo.name if photo.registered else "-", f"{photo.exposure:.6g}",
                      photo.exposure_source, "yes" if photo.registered else "[red]no")
    console.print(table)
    low, high = report.exposure_range
    console.print(f"placed {len(report.registered)} / {len(report.photos)} photos ({report.matcher} matching), "
                  f"{report.num_points} points, mean reprojection error {report.mean_reprojection_error:.3f} px")
    console.print(f"camera {report.camera_model} {report.width}x{report.height}; exposures {low:.6g} s to "
                  f"{high:.6g} s ({report.exposure_stops:.1f} stops)")
    if report.reference_iso or report.reference_f_number:
        console.print(f"exposures are relative to ISO {report.reference_iso or '-'}, f/{report.reference_f_number or '-'}")
    for note in report.warnings:
        console.print(f"[yellow]warning:[/yellow] {note}")
    if report.failed:
        console.print(f"[red]not placed:[/red] {', '.join(report.failed)}")
    console.print(f"next: mono-hdr train gs --data {report.out} --out outputs/{report.out.name}")


def process_data_command(config: ProcessDataConfig) -> None:
    """`mono-hdr process-data`: run it and print the report."""
    console = Console()
    print_report(process_data(config, console), console)
