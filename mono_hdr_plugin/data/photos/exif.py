"""The EXIF fields process-data uses, read from a photo and written by the simulated camera.

Tag numbers are those of EXIF 2.32. Orientation is applied by Pillow's ImageOps.exif_transpose
when a photo is opened, so it is written here but never read.
"""

import math
from dataclasses import dataclass
from datetime import datetime
from fractions import Fraction

from PIL import Image
from PIL.TiffImagePlugin import IFDRational

EXIF_IFD = 0x8769
GPS_IFD = 0x8825
GPS_LATITUDE_REF, GPS_LATITUDE, GPS_LONGITUDE_REF, GPS_LONGITUDE = 1, 2, 3, 4
GPS_ALTITUDE_REF, GPS_ALTITUDE = 5, 6
TAG_MAKE, TAG_MODEL, TAG_ORIENTATION = 0x010F, 0x0110, 0x0112
TAG_EXPOSURE_TIME, TAG_F_NUMBER, TAG_ISO, TAG_FOCAL_35MM = 0x829A, 0x829D, 0x8827, 0xA405
TAG_DATE_TIME_ORIGINAL, TAG_SUBSEC_TIME_ORIGINAL = 0x9003, 0x9291
TAG_EXPOSURE_MODE = 0xA402
TAG_WHITE_BALANCE = 0xA403
WHITE_BALANCE_MODES = {0: "auto", 1: "manual"}
"""EXIF WhiteBalance values: the mode only; the gains a camera applied are in its maker notes."""
EXPOSURE_MODE_AUTO_BRACKET = 2
"""ExposureMode value a camera writes for every photo of an automatic exposure bracket."""
DATE_FORMAT = "%Y:%m:%d %H:%M:%S"


@dataclass
class PhotoExif:
    """The EXIF fields process-data uses (None when absent)."""

    exposure_time: float | None = None
    f_number: float | None = None
    iso: float | None = None
    focal_35mm: float | None = None
    camera: str | None = None
    timestamp: float | None = None
    """Capture time in seconds (DateTimeOriginal plus SubSecTimeOriginal, no time zone): only
    differences between photos are used."""
    auto_bracket: bool = False
    """ExposureMode says the camera took this photo as part of an automatic exposure bracket."""
    gps: tuple[float, float, float] | None = None
    """(latitude, longitude in degrees, north and east positive; altitude in metres, 0 when absent)."""
    white_balance: str | None = None
    """WhiteBalance: "auto" (the camera balanced each photo itself) or "manual"."""


def exif_number(value) -> float | None:
    """An EXIF number (rational, int, or a tuple of them) as a float; None when unusable."""
    if isinstance(value, (tuple, list)):
        value = value[0] if value else None
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) and number > 0 else None


def exif_timestamp(date_time, subseconds=None) -> float | None:
    """`YYYY:MM:DD HH:MM:SS` (and its SubSecTime digits) as seconds; None when unreadable."""
    if not isinstance(date_time, str):
        return None
    try:
        seconds = datetime.strptime(date_time.strip("\x00 "), DATE_FORMAT).timestamp()
    except ValueError:
        return None
    digits = str(subseconds or "").strip("\x00 ")
    return seconds + (float(f"0.{digits}") if digits.isdigit() else 0.0)


def gps_degrees(value, reference) -> float | None:
    """An EXIF GPS coordinate (degrees, minutes, seconds as rationals) with its N/S/E/W reference."""
    if not isinstance(value, (tuple, list)) or len(value) != 3:
        return None
    try:
        degrees = float(value[0]) + float(value[1]) / 60 + float(value[2]) / 3600
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    if not math.isfinite(degrees):
        return None
    return -degrees if str(reference).strip("\x00 ").upper() in ("S", "W") else degrees


def read_gps(exif: Image.Exif) -> tuple[float, float, float] | None:
    """(latitude, longitude, altitude) from the GPS block, or None without a usable position."""
    block = exif.get_ifd(GPS_IFD)
    latitude = gps_degrees(block.get(GPS_LATITUDE), block.get(GPS_LATITUDE_REF))
    longitude = gps_degrees(block.get(GPS_LONGITUDE), block.get(GPS_LONGITUDE_REF))
    if latitude is None or longitude is None or abs(latitude) > 90 or abs(longitude) > 180:
        return None
    altitude = exif_number(block.get(GPS_ALTITUDE)) or 0.0  # exif_number drops 0 and negatives: 0 then
    below_sea = block.get(GPS_ALTITUDE_REF) in (1, b"\x01")
    return latitude, longitude, -altitude if below_sea else altitude


def read_exif(image: Image.Image) -> PhotoExif:
    """The exposure, aperture, ISO, 35 mm focal length, camera, capture time, exposure and white
    balance modes."""
    exif = image.getexif()
    details = exif.get_ifd(EXIF_IFD)

    def tag(number):
        return details.get(number, exif.get(number))  # TIFFs may keep them in the main IFD

    camera = " ".join(str(exif.get(t, "")).strip("\x00 ") for t in (TAG_MAKE, TAG_MODEL)).strip()
    return PhotoExif(
        exposure_time=exif_number(tag(TAG_EXPOSURE_TIME)),
        f_number=exif_number(tag(TAG_F_NUMBER)),
        iso=exif_number(tag(TAG_ISO)),
        focal_35mm=exif_number(tag(TAG_FOCAL_35MM)),
        camera=camera or None,
        timestamp=exif_timestamp(tag(TAG_DATE_TIME_ORIGINAL), tag(TAG_SUBSEC_TIME_ORIGINAL)),
        auto_bracket=tag(TAG_EXPOSURE_MODE) == EXPOSURE_MODE_AUTO_BRACKET,
        gps=read_gps(exif),
        white_balance=WHITE_BALANCE_MODES.get(tag(TAG_WHITE_BALANCE)),
    )


def _rational(value: Fraction | float) -> IFDRational:
    """Pillow writes EXIF rationals from IFDRational, not from Fraction."""
    value = Fraction(value).limit_denominator(1_000_000)
    return IFDRational(value.numerator, value.denominator)


def make_exif(
    exposure: Fraction | None = None,
    iso: int | None = None,
    f_number: Fraction | None = None,
    focal_35mm: int | None = None,
    model: str | None = "StudioCam",
    orientation: int | None = None,
    timestamp: float | None = None,
    exposure_mode: int | None = None,
    gps: tuple[float, float, float] | None = None,
    white_balance: int | None = None,
) -> Image.Exif:
    """An Exif block with the given fields, as a camera writes them (pass it to Image.save(exif=...))."""
    exif = Image.Exif()
    if model:
        exif[TAG_MAKE], exif[TAG_MODEL] = "Mono-HDR", model
    if orientation:
        exif[TAG_ORIENTATION] = orientation
    details = exif.get_ifd(EXIF_IFD)
    for tag, value in ((TAG_EXPOSURE_TIME, exposure), (TAG_F_NUMBER, f_number)):
        if value is not None:
            details[tag] = _rational(value)
    numbers = ((TAG_ISO, iso), (TAG_FOCAL_35MM, focal_35mm), (TAG_EXPOSURE_MODE, exposure_mode))
    for tag, number in (*numbers, (TAG_WHITE_BALANCE, white_balance)):
        if number is not None:
            details[tag] = number
    if gps is not None:
        block = exif.get_ifd(GPS_IFD)
        for position, reference, coordinate, signs in (
            (GPS_LATITUDE, GPS_LATITUDE_REF, gps[0], "NS"),
            (GPS_LONGITUDE, GPS_LONGITUDE_REF, gps[1], "EW"),
        ):
            degrees = abs(coordinate)
            minutes = (degrees - int(degrees)) * 60
            seconds = (minutes - int(minutes)) * 60
            block[reference] = signs[coordinate < 0]
            block[position] = (_rational(int(degrees)), _rational(int(minutes)), _rational(round(seconds, 4)))
        block[GPS_ALTITUDE_REF] = int(gps[2] < 0)
        block[GPS_ALTITUDE] = _rational(round(abs(gps[2]), 3))
    if timestamp is not None:
        moment = datetime.fromtimestamp(timestamp)
        details[TAG_DATE_TIME_ORIGINAL] = moment.strftime(DATE_FORMAT)
        details[TAG_SUBSEC_TIME_ORIGINAL] = f"{moment.microsecond // 1000:03d}"
    return exif
