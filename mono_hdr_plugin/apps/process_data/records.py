"""What the stages learn about each photo, bracket set and video, passed from stage to stage and
written in the report."""

from dataclasses import dataclass
from typing import Literal

ExposureSource = Literal["exif", "raw", "csv", "flag", "unknown"]


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
    white_balance: str | None = None
    """EXIF WhiteBalance: "auto" (the camera balanced it itself: the trainer learns its gains), "manual"."""


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
