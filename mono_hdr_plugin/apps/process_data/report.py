"""Stage 6: the report of what process-data did, written to OUT/process_data.json and printed."""

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from rich.console import Console
from rich.table import Table

from mono_hdr_plugin.apps.process_data.records import HdrView, PhotoRecord, VideoRecord
from mono_hdr_plugin.apps.process_data.sfm import MapperAttempt


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
    mapper: str = "incremental"
    """The structure-from-motion mapper whose model was kept."""
    mapper_attempts: list[MapperAttempt] = field(default_factory=list)
    """Every mapper that ran: photos placed, reprojection error, seconds."""
    gps_rms_m: float | None = None
    """RMS metres between camera centres and the photos' EXIF GPS after a similarity fit (None
    without GPS): a check of the poses against an independent measurement, GPS error included."""

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
        return {
            **asdict(self),
            "out": str(self.out),
            "failed": self.failed,
            "exposure_range": self.exposure_range,
            "exposures_known": self.exposures_known,
        }


def _seconds(value: float | None) -> str:
    return "unknown" if value is None else f"{value:.6g}"


def print_report(report: ProcessReport, console: Console) -> None:
    """Per-photo table, summary, HDR views and warnings."""
    table = Table(title=f"process-data -> {report.out}")
    for column in ("photo", "dataset image", "exposure (s)", "source", "placed", "bracket"):
        table.add_column(column)
    for photo in report.photos:
        bracket = "-" if photo.bracket is None else f"{photo.bracket} ({photo.bracket_exposure:.3g}x)"
        table.add_row(
            photo.source,
            photo.name if photo.view else "-",
            _seconds(photo.exposure),
            photo.exposure_source,
            "yes" if photo.registered else "[red]no",
            bracket,
        )
    console.print(table)
    if report.video is not None:
        video = report.video
        console.print(
            f"video {video.source}: kept {video.kept} of {video.candidates} candidate frames "
            f"({video.fps:g} per second, the sharpest of each three, blurred ones dropped)"
        )
    _print_placement(report, console)
    exposures = (
        "exposures unknown (learned in training)"
        if report.exposure_range is None
        else f"exposures {report.exposure_range[0]:.6g} s to {report.exposure_range[1]:.6g} s "
        f"({report.exposure_stops:.1f} stops)"
    )
    console.print(f"camera {report.camera_model} {report.width}x{report.height}; {exposures}")
    if report.reference_iso or report.reference_f_number:
        console.print(
            f"exposures are relative to ISO {report.reference_iso or '-'}, f/{report.reference_f_number or '-'}"
        )
    singles = len(report.views) - len(report.hdr_views)
    console.print(
        f"{len(report.views)} views: {len(report.hdr_views)} HDR (merged brackets), {singles} single-exposure "
        f"LDR; {len(report.test_views)} held out for testing"
    )
    for hdr_view in report.hdr_views:
        how = "ratios measured from the pixels" if hdr_view.exposures_estimated else "exposures from metadata"
        console.print(
            f"  HDR {hdr_view.name}: {len(hdr_view.sources)} photos ({how}), dynamic range "
            f"{hdr_view.dynamic_range_stops:.1f} stops"
        )
    if report.response:
        console.print(f"camera response: {report.response}")
    if report.ignored:
        console.print(f"ignored (the RAW file of the same name is used): {', '.join(report.ignored)}")
    for note in report.warnings:
        console.print(f"[yellow]warning:[/yellow] {note}")
    if report.failed:
        console.print(f"[red]left out (not placed):[/red] {', '.join(report.failed)}")
    console.print(f"next: mono-hdr train gs --data {report.out} --out outputs/{report.out.name}")


def _print_placement(report: ProcessReport, console: Console) -> None:
    """Photos placed, by which mapper (and what each one tried placed), points, error, the GPS check."""
    tried = ", ".join(f"{attempt.mapper} {attempt.placed}" for attempt in report.mapper_attempts)
    console.print(
        f"placed {len(report.registered)} / {len(report.photos)} photos ({report.matcher} matching, "
        f"{report.mapper} mapper{f'; placed by each: {tried}' if len(report.mapper_attempts) > 1 else ''}), "
        f"{report.num_points} points, mean reprojection error {report.mean_reprojection_error:.3f} px"
    )
    if report.gps_rms_m is not None:
        console.print(f"camera positions against the photos' GPS: {report.gps_rms_m:.1f} m RMS after a similarity fit")
