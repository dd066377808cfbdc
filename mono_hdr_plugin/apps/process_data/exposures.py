"""Stage 2: each photo's exposure, first source that has it: EXIF ExposureTime (RAW: LibRaw's
metadata; ISO and aperture folded in when they vary between photos), the --exposure-csv row, the
--exposure value; with none of them anywhere the exposures are unknown and the trainer learns them."""

import csv
import math
from collections import Counter
from pathlib import Path

from mono_hdr_plugin.apps.process_data.photos import StagedPhoto
from mono_hdr_plugin.apps.process_data.records import ExposureSource, PhotoRecord
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.layouts.common import check_exposure
from mono_hdr_plugin.data.photos.exif import PhotoExif

WIDE_RANGE_STOPS = 8.0
"""Exposures spanning more stops than this are worth a warning: more than one sensor's range."""


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


def relative_exposure(
    time: float, iso: float, f_number: float, reference_iso: float, reference_f_number: float
) -> float:
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


def reference_settings(exifs: list[PhotoExif]) -> dict:
    """{"iso", "f_number"}: the most common value of each among the timed photos, None when it does not vary."""
    timed = [exif for exif in exifs if exif.exposure_time is not None]
    isos, f_numbers = {e.iso for e in timed if e.iso}, {e.f_number for e in timed if e.f_number}
    return {
        "iso": _most_common([e.iso for e in timed]) if len(isos) > 1 else None,
        "f_number": _most_common([e.f_number for e in timed]) if len(f_numbers) > 1 else None,
    }


def assign_exposures(
    sources: list[str],
    exifs: list[PhotoExif],
    csv_table: dict[str, float],
    flag: float | None,
    csv_path: Path | None = None,
    raw: list[bool] | None = None,
) -> tuple[list[tuple[float | None, ExposureSource]], dict]:
    """(seconds or None, source) per photo and the reference ISO/aperture used when those vary.

    EXIF (or RAW metadata) first, then the CSV row, then --exposure (checked by the flag rules).
    ISO and aperture are folded in only when they vary between the photos, so a fixed-setting
    capture keeps its exact times. When no photo has an exposure from any source they are all
    unknown (the trainer learns them); some known and some not is an error, since the unknown
    ones would have no scale.
    """
    raw = raw or [False] * len(sources)
    unknown = sorted(set(csv_table) - set(sources))
    if unknown:
        raise DatasetError(
            f"{csv_path}: rows for photos that are not in --images: {', '.join(unknown[:5])}; "
            "fix the file names in the CSV"
        )
    reference = reference_settings(exifs)
    # A setting that does not vary is left out (ratio exactly 1); a photo missing a varying one
    # is assumed to have the reference value (exposure_warnings says so).
    iso_reference, f_reference = reference["iso"] or 1.0, reference["f_number"] or 1.0
    exposures: list[tuple[float | None, ExposureSource]] = []
    lacking: list[str] = []
    for source, exif, is_raw_photo in zip(sources, exifs, raw):
        if exif.exposure_time is not None:
            iso = (exif.iso or iso_reference) if reference["iso"] else 1.0
            f_number = (exif.f_number or f_reference) if reference["f_number"] else 1.0
            exposures.append(
                (
                    relative_exposure(exif.exposure_time, iso, f_number, iso_reference, f_reference),
                    "raw" if is_raw_photo else "exif",
                )
            )
        elif source in csv_table:
            exposures.append((csv_table[source], "csv"))
        elif flag is not None:
            exposures.append((float(flag), "flag"))
        else:
            exposures.append((None, "unknown"))
            lacking.append(source)
    if lacking and len(lacking) < len(sources):
        raise DatasetError(
            f"{len(lacking)} photo(s) have no exposure time in their EXIF ({', '.join(lacking[:5])}"
            f"{', ...' if len(lacking) > 5 else ''}) while the others have one; pass --exposure "
            "SECONDS (one time for all) or --exposure-csv FILE with `file name,seconds` rows"
        )
    return exposures, reference


def photo_records(
    staged: list[StagedPhoto], csv_table: dict[str, float], flag: float | None, csv_path: Path | None
) -> tuple[list[PhotoRecord], dict]:
    """A record of each staged photo with its exposure; the reference ISO/aperture (assign_exposures)."""
    exposures, reference = assign_exposures(
        [s.source.name for s in staged], [s.exif for s in staged], csv_table, flag, csv_path, [s.raw for s in staged]
    )
    photos = [
        PhotoRecord(
            source=stage.source.name,
            name=stage.name,
            exposure=time,
            exposure_source=origin,
            iso=stage.exif.iso,
            f_number=stage.exif.f_number,
            raw=stage.raw,
            white_balance=stage.exif.white_balance,
        )
        for stage, (time, origin) in zip(staged, exposures)
    ]
    return photos, reference


def exposure_warnings(photos: list[PhotoRecord], reference: dict) -> list[str]:
    """Notes on the exposure spread of the dataset's views (bracket members aside): unknown, one shared
    exposure, a very wide range, folded ISO/aperture."""
    exposures = [photo.exposure for photo in photos if photo.view and photo.exposure is not None]
    if not exposures:
        return [
            "no exposure times (EXIF, --exposure-csv, --exposure): treating every photo as one unknown exposure "
            "that training learns per view (--learn-exposure), and merging only photos of one viewpoint that line "
            "up, their ratios measured from the pixels; pass --exposure SECONDS or --exposure-csv FILE to give them"
        ]
    notes = []
    low, high = min(exposures), max(exposures)
    if math.isclose(low, high, rel_tol=1e-3):
        notes.append(
            f"every photo has the same exposure ({low:.6g} s): the single-exposure setting "
            "Mono-HDR is made for; HDR is recovered up to one overall scale"
        )
    elif math.log2(high / low) > WIDE_RANGE_STOPS:
        notes.append(
            f"exposures span {math.log2(high / low):.1f} stops ({low:.6g} s to {high:.6g} s), more "
            "than one sensor can hold: fine, but check the darkest and brightest photos are usable"
        )
    missing_settings = [
        p.source
        for p in photos
        if (reference["iso"] and p.iso is None and p.exposure_source == "exif")
        or (reference["f_number"] and p.f_number is None and p.exposure_source == "exif")
    ]
    if missing_settings:
        notes.append(
            f"ISO or aperture varies but is missing in {', '.join(missing_settings[:5])}; the reference "
            "value was assumed for them"
        )
    return notes
