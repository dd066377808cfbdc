"""Bracket sets: photos of one viewpoint at several exposures, found and merged into linear HDR.

Finding them. Photos are taken in file order, and two neighbours show one viewpoint when
- the camera says so: both are marked as an automatic exposure bracket (EXIF ExposureMode) and
  the second was taken within `max_gap` seconds of the end of the first (a very dark or very
  bright bracket member often has too few features for structure from motion to place it, or
  places it a little off); or
- structure from motion put them at (almost) the same pose and, when both carry a capture time,
  within the gap; or
- one of them has no trustworthy pose and it was taken within the gap (bracket members too dark
  or too bright for structure from motion to place well, from a camera that does not mark its
  brackets).
A run of one viewpoint is then cut wherever an exposure repeats, so two brackets shot at one
place stay two sets. Before merging, `aligned_members` checks the pixels: a member whose
linearised pixels are not a constant multiple of its neighbour's, in place, shows something else
(another viewpoint, something moved) and is left out. A set whose exposures span less than
MIN_BRACKET_STOPS is no bracket.

Merging them is colour-hdri's (colour-science): Debevec & Malik (1997) recover the camera
response from the sets' intensity histograms (Grossberg & Nayar 2003 sampling, so small shifts
between the photos do not matter), and the merge is the weighted average of linearised pixels
divided by their exposures, with weights that vanish at black and at clipping.
"""

import math
import warnings
from dataclasses import dataclass
from functools import partial

import numpy as np

from mono_hdr_plugin.data.errors import DatasetError

RESPONSE_LEVELS = 256
"""The recovered response maps each of 256 code values (8-bit photos) to relative linear exposure."""
SAME_EXPOSURE = 0.03
"""Exposures within 3 % (a tenth of a third-stop step) are the same setting."""
WELL_EXPOSED = (0.2, 0.9)
"""Code values of the brighter photo trusted to compare two exposures: the darker photo is then
above its noise floor, and the brighter one below clipping."""
MIN_SHARED_PIXELS = 20
DARK_FLOOR = 0.05
"""Code value below which a pixel of the darker photo is too close to black (noise, quantisation,
JPEG) to measure an exposure ratio with."""
ALIGNED_LOG_SPREAD = 0.25
"""Neighbours in a bracket whose per-pixel log exposure ratios spread (median absolute deviation)
more than this do not show one view (the spreads it was chosen from: docs/own_photos.md,
"How the bracket thresholds were chosen")."""
ALIGN_SIZE = 128
"""Alignment is judged on block means at most this many pixels on the long side: block means
average sensor noise away, and one pixel there (about 30 px of a 4000 px photo) is the blur a
merge of slightly shifted photos would show."""
ALIGN_FAR = 4
"""Shift, in pixels of the block means, that shows what the same photos look like misaligned."""
ALIGN_NEAR_TOLERANCE = 1.1
"""In place, two photos of one view agree at least about as well as shifted by one pixel (0.6-1.0
times the spread for brackets; 1.2-1.6 for a copy shifted by 1-2 px: docs/own_photos.md)."""
ALIGN_FAR_FRACTION = 0.45
"""In place, two photos of one view agree much better than shifted by ALIGN_FAR pixels (0.1-0.4
times for brackets, 0.5-0.7 for viewpoints 1-2 degrees apart, about 1 for unrelated photos)."""
MIN_BRACKET_STOPS = 2 / 3
"""A set whose exposures span less than 2/3 stop is no bracket but one exposure shot again: it
would add at most 2/3 stop to the merge's range, auto-exposure moves more than that between
single photos, and a ratio that small measured from the pixels is within what JPEG tone mapping
and vignetting change between two shots (a neighbouring viewpoint measured 1.04x: issue 33)."""
MIN_RESPONSE_STOPS = 1.0
"""Debevec's recovery links code values whose exposures differ by the sets' ratios; on noisy JPEG
brackets of a 14-stop scene its error (max log, codes 20-250) is 0.1-0.16 from one stop up, 0.24
at 2/3 stop and 1.2 at 1.04x, with a third of a stop's error at mid grey (docs/own_photos.md)."""
MIN_RESPONSE_CODES = 0.95
"""The code values well exposed in two photos of one set must cover this fraction of the trusted
range (CONSTRAINED): at 100 % the curve is within 0.25 in log, at 70-90 % (scenes of 3-4 stops)
off by 0.6-1.9 where nothing constrains it."""
RESPONSE_BLACK = 0.01
"""A camera response maps black to at most this fraction of white (sRGB: 0, gamma 2.2: 0)."""
RESPONSE_CHANNELS = 1.5
"""Colour channels of one camera's response differ by at most this factor between black and white
(each is 1 at white; a camera's white balance makes grey grey)."""
RESPONSE_FALL = 0.1
"""Debevec's curve, before it is made increasing, may fall by at most this fraction anywhere."""
RESPONSE_PIXELS = 200_000
"""Photos are subsampled to about this many pixels for the response recovery (it uses histograms)."""
RESPONSE_SAMPLES = 250
"""Histogram quantiles per photo that constrain the response (fewer than colour-hdri's default
1000, which costs far more for the same curve: docs/own_photos.md)."""
CONSTRAINED = (0.08, 0.9)
"""Code values between which Debevec's recovered response is trusted (see continue_ends)."""
EDGE_WINDOW = 30
RESPONSE_SMOOTHNESS = 100.0
"""Debevec's lambda: smoother than colour-hdri's 30, which lets noisy JPEG histograms bend the dark
end of the response (docs/own_photos.md)."""
MERGE_ROWS = 256
"""Merge this many image rows at a time: memory stays bounded for large photos."""


@dataclass
class BracketCandidate:
    """What bracket detection knows about one photo."""

    name: str
    exposure: float | None
    """Relative exposure (seconds at the reference ISO and aperture), None when unknown."""
    timestamp: float | None = None
    auto_bracket: bool = False
    center: np.ndarray | None = None
    """[3] camera centre from structure from motion; None when the photo was not placed, or placed
    from so few points that its pose is not to be trusted (a very dark or bright bracket member)."""
    rotation: np.ndarray | None = None
    """[3, 3] camera-to-world rotation from structure from motion."""


@dataclass(frozen=True)
class BracketTolerances:
    """How close two photos must be to count as one viewpoint."""

    max_gap: float = 2.0
    """Seconds from the end of one photo to the start of the next."""
    position: float = 0.03
    """Distance between camera centres, as a fraction of the scene scale (structure from motion does
    not place the members of a tripod bracket exactly together: docs/own_photos.md)."""
    angle_deg: float = 3.0
    """Angle between the camera orientations."""


class UnreliableResponse(ValueError):
    """The brackets cannot carry a camera response, or the fitted one is implausible: the message says why."""


def same_exposure(a: float, b: float) -> bool:
    return abs(math.log(a / b)) < SAME_EXPOSURE


def spread_stops(exposures: list[float]) -> float:
    """How many stops the exposures span."""
    return math.log2(max(exposures) / min(exposures))


def _rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    cosine = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cosine, -1.0, 1.0))))


def _linked(a: BracketCandidate, b: BracketCandidate, scale: float, tolerances: BracketTolerances) -> bool:
    """Whether photo b, taken after a, shows the same viewpoint."""
    if a.timestamp is not None and b.timestamp is not None:
        if abs(b.timestamp - a.timestamp) > tolerances.max_gap + (a.exposure or 0.0):
            return False
        if a.auto_bracket and b.auto_bracket or a.center is None or b.center is None:
            return True
    if a.center is None or b.center is None:
        return False
    assert a.rotation is not None and b.rotation is not None  # structure from motion sets centre and rotation together
    return (
        float(np.linalg.norm(a.center - b.center)) <= tolerances.position * scale
        and _rotation_angle_deg(a.rotation, b.rotation) <= tolerances.angle_deg
    )


def _check_not_all_equal(run: list[int], photos: list[BracketCandidate]) -> None:
    """A camera bracket whose exposures are all equal cannot be merged: the bracket varied something else."""
    members = [photos[i] for i in run]
    exposures = [p.exposure for p in members if p.exposure is not None]
    if (
        len(members) > 1
        and all(p.auto_bracket for p in members)
        and len(exposures) == len(members)
        and all(same_exposure(exposure, exposures[0]) for exposure in exposures)
    ):
        raise DatasetError(
            f"{', '.join(p.name for p in members)}: the camera marked these photos as one exposure "
            f"bracket, but all have the exposure {members[0].exposure:.6g} s, so there is nothing "
            "to merge. The camera may have bracketed focus or white balance: check its bracketing "
            "mode, or pass --no-brackets to use them as single photos"
        )


def detect_brackets(
    photos: list[BracketCandidate], scale: float, tolerances: BracketTolerances = BracketTolerances()
) -> list[list[int]]:
    """Partition photo indices (in file order) into viewpoint sets; a set of 2+ photos is a bracket.

    scale: the scene's size in structure-from-motion units (for the position tolerance).
    """
    runs: list[list[int]] = []
    for index, photo in enumerate(photos):
        if runs and _linked(photos[runs[-1][-1]], photo, scale, tolerances):
            runs[-1].append(index)
        else:
            runs.append([index])
    sets: list[list[int]] = []
    for run in runs:
        _check_not_all_equal(run, photos)
        sets.append([run[0]])
        for index in run[1:]:
            exposure = photos[index].exposure
            others = [photos[j].exposure for j in sets[-1]]
            repeats = exposure is not None and any(
                other is not None and same_exposure(exposure, other) for other in others
            )
            if repeats:
                sets.append([index])
            else:
                sets[-1].append(index)
    return sets


# ---------------------------------------------------------------- response and merge


def _stack(images: list[np.ndarray], exposures: list[float]):
    """A colour-hdri ImageStack whose photometric exposure 1 / L is each photo's relative exposure.

    colour-hdri computes L = N^2 / t * k / S (k = 12.5); with N = 1 and S = k, 1 / L = t.
    """
    from colour_hdri import Image, ImageStack, Metadata

    stack = ImageStack()
    for image, exposure in sorted(zip(images, exposures), key=lambda pair: pair[1]):
        stack.append(
            Image(data=np.asarray(image, np.float64), metadata=Metadata(f_number=1.0, exposure_time=exposure, iso=12.5))
        )
    return stack


def merge_weights(values: np.ndarray, response: np.ndarray | None) -> np.ndarray:
    """Trust of each code value in [0, 1] of a bracket photo: its linear value, faded out at clipping.

    Shot noise makes a pixel's variance grow with its linear value x, so the inverse-variance
    weight of its estimate x / t is proportional to t, that is to x itself: of two photos the
    longer exposure is trusted more, up to where it clips. The fade is colour-hdri's anchored
    double sigmoid, from 0.8 to 0.975. Neither factor depends on the image's own range (the
    Debevec hat in colour-hdri is divided by the image's largest weight), so every row block of
    a merge is weighted alike.
    """
    from colour_hdri import double_sigmoid_anchored_function

    fade = double_sigmoid_anchored_function(values, domain_l_in=-2.0, domain_l_out=-1.0)
    return linearise(values, response) * fade


def check_exposures_differ(exposures: list[float], names: list[str]) -> None:
    if len(exposures) < 2 or all(same_exposure(e, exposures[0]) for e in exposures):
        raise DatasetError(
            f"{', '.join(names)}: a bracket needs photos at two or more different exposures, these "
            f"have {', '.join(f'{e:.6g}' for e in exposures)} s; remove the set or fix the exposures"
        )


def response_sample(image: np.ndarray) -> np.ndarray:
    """Every k-th pixel of each k-th row, about RESPONSE_PIXELS in all: enough for the response's histograms."""
    step = max(1, int(math.sqrt(image.shape[0] * image.shape[1] / RESPONSE_PIXELS)))
    return image[::step, ::step]


def recover_response(brackets: list[tuple[list[np.ndarray], list[float]]]) -> np.ndarray:
    """Camera response [256, 3]: code value k / 255 -> relative linear exposure, 1 at white.

    Debevec & Malik (1997) on each bracket (photos in [0, 1], subsampled with response_sample, and
    their relative exposures); one camera has one response, so the sets' curves are averaged in log
    space. Made strictly increasing, since a response with a flat or falling step cannot be
    inverted. UnreliableResponse when the brackets cannot carry a curve (response_evidence) or the
    curve is implausible (response_problem).
    """
    from colour_hdri import camera_response_functions_Debevec1997

    missing_evidence = response_evidence(brackets)
    if missing_evidence:
        raise UnreliableResponse(missing_evidence)
    curves = []
    for images, exposures in brackets:
        stack = _stack(images, exposures)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # colour's notes on zero pixels: the weights exclude them
            curve = camera_response_functions_Debevec1997(
                stack,
                sampling_function_kwargs={"samples": RESPONSE_SAMPLES},
                l_s=RESPONSE_SMOOTHNESS,
                n=RESPONSE_LEVELS,
            )
        curves.append(np.log(np.clip(curve, 1e-6, None)))
    fitted = continue_ends(np.exp(np.mean(curves, axis=0)))
    problem = response_problem(fitted / fitted[-1])
    if problem:
        raise UnreliableResponse(problem)
    response = np.maximum.accumulate(np.clip(fitted, 1e-9, None), axis=0)
    response += np.arange(RESPONSE_LEVELS)[:, None] * 1e-9  # strictly increasing
    return (response / response[-1]).astype(np.float64)


def response_evidence(brackets: list[tuple[list[np.ndarray], list[float]]]) -> str | None:
    """What the brackets lack to carry a response (None: enough): an exposure spread of
    MIN_RESPONSE_STOPS in some set, and codes well exposed in two of its photos over
    MIN_RESPONSE_CODES of the trusted range."""
    widest = max(spread_stops(exposures) for _, exposures in brackets)
    if widest < MIN_RESPONSE_STOPS:
        return f"the widest bracket spans {widest:.2f} stops, the response needs {MIN_RESPONSE_STOPS:g} or more"
    covered = np.zeros(RESPONSE_LEVELS, bool)
    trusted = slice(*(int(round(limit * (RESPONSE_LEVELS - 1))) for limit in CONSTRAINED))
    for images, exposures in brackets:
        order = np.argsort(exposures)
        for darker, brighter in zip(order, order[1:]):
            a, b = images[darker], images[brighter]
            both = (a > CONSTRAINED[0]) & (a < CONSTRAINED[1]) & (b > CONSTRAINED[0]) & (b < CONSTRAINED[1])
            for codes in (a[both], b[both]):
                covered[np.round(codes * (RESPONSE_LEVELS - 1)).astype(int)] = True
    coverage = float(covered[trusted].mean())
    if coverage < MIN_RESPONSE_CODES:
        return (
            f"code values well exposed in two photos of a bracket cover {coverage:.0%} of the range, "
            f"the response needs {MIN_RESPONSE_CODES:.0%}"
        )
    return None


def response_problem(response: np.ndarray) -> str | None:
    """Why a fitted response [256, 3] (1 at white) is implausible for a camera, or None."""
    trusted = slice(*(int(round(limit * (RESPONSE_LEVELS - 1))) for limit in CONSTRAINED))
    if response[0].max() > RESPONSE_BLACK:
        return f"it maps black to {response[0].max():.2f} of white, not to about 0"
    peak = np.maximum.accumulate(response, axis=0)
    fall = float((1 - response[peak > 0] / peak[peak > 0]).max())
    if fall > RESPONSE_FALL:
        return f"it falls by {fall:.0%} on the way up to white"
    channels = float((response[trusted].max(-1) / response[trusted].min(-1)).max())
    if channels > RESPONSE_CHANNELS:
        return f"its colour channels differ by up to {channels:.1f}x (a colour cast)"
    return None


def continue_ends(response: np.ndarray) -> np.ndarray:
    """The response [256, 3] with its ends replaced by power laws fitted next to them.

    Debevec's weights vanish at black and white, so few samples and little smoothing hold the
    curve there: on noise-free gamma-2.2 brackets its top 10 codes bend up by 0.38 in log
    exposure and its bottom 10 by 0.29, which shifts every merge that contains a clipped or
    black pixel. Below code CONSTRAINED[0] and above CONSTRAINED[1] the curve follows the
    log-log line fitted over the EDGE_WINDOW codes inside each limit.
    """
    codes = np.arange(RESPONSE_LEVELS, dtype=np.float64)
    low, high = (int(round(limit * (RESPONSE_LEVELS - 1))) for limit in CONSTRAINED)
    log_codes, log_response = np.log(np.maximum(codes, 0.5)), np.log(np.clip(response, 1e-12, None))
    result = log_response.copy()
    for inside, outside in (
        (slice(low, low + EDGE_WINDOW), slice(0, low)),
        (slice(high - EDGE_WINDOW, high), slice(high, RESPONSE_LEVELS)),
    ):
        for channel in range(response.shape[1]):
            slope, intercept = np.polyfit(log_codes[inside], log_response[inside, channel], 1)
            result[outside, channel] = slope * log_codes[outside] + intercept
    return np.exp(result)


def linearise(image: np.ndarray, response: np.ndarray | None) -> np.ndarray:
    """Code values [..., 3] in [0, 1] -> relative linear exposure through the response (None: already linear)."""
    if response is None:
        return np.asarray(image, np.float64)
    levels = np.linspace(0.0, 1.0, len(response))
    return np.stack([np.interp(image[..., c], levels, response[:, c]) for c in range(3)], -1)


def brightness_order(images: list[np.ndarray]) -> list[int]:
    """Indices of the photos from the darkest to the brightest (mean pixel value)."""
    return sorted(range(len(images)), key=lambda i: float(np.mean(images[i])))


def alignment_view(image: np.ndarray) -> np.ndarray:
    """Block means [h, w, 3] of a photo, at most ALIGN_SIZE pixels on the long side, for lines_up."""
    factor = max(1, math.ceil(max(image.shape[:2]) / ALIGN_SIZE))
    height, width = image.shape[0] // factor * factor, image.shape[1] // factor * factor
    blocks = image[:height, :width].reshape(height // factor, factor, width // factor, factor, -1)
    return blocks.mean((1, 3))


def lines_up(darker: np.ndarray, brighter: np.ndarray, response: np.ndarray | None) -> bool:
    """Whether two photos of a bracket (alignment_view, the first the shorter exposure) show the same view.

    Over the pixels well exposed in the brighter photo the darker one must not be clipped (a
    shorter exposure cannot be brighter). Where the darker one is above black too, the ratio of the
    linearised pixels (the exposure ratio, for photos of one view) must be nearly the same
    everywhere, measured as the spread (median absolute deviation) of its logs: at most
    ALIGNED_LOG_SPREAD, no more than ALIGN_NEAR_TOLERANCE times the spread with one photo shifted
    by a pixel (another viewpoint agrees better shifted), and at most ALIGN_FAR_FRACTION of the
    spread shifted by ALIGN_FAR pixels (photos of one view agree in place far better than
    misaligned; two viewpoints, or a featureless view, do not). Too few shared pixels is no
    evidence either way: True.
    """
    # Whole pixels: a channel beside a clipped one is unreliable (demosaicing, highlight recovery).
    well_exposed = ((brighter > WELL_EXPOSED[0]) & (brighter < WELL_EXPOSED[1])).all(-1)
    if well_exposed.sum() < MIN_SHARED_PIXELS:
        return True
    if np.mean(darker[well_exposed] >= WELL_EXPOSED[1]) > 0.05:
        return False
    above_black = (darker > DARK_FLOOR).all(-1)
    if (well_exposed & above_black).sum() < MIN_SHARED_PIXELS:
        return True
    log_dark, log_bright = (np.log(np.clip(linearise(x, response).mean(-1), 1e-6, None)) for x in (darker, brighter))
    spread = partial(_ratio_spread, log_dark, log_bright, np.asarray(above_black), np.asarray(well_exposed))
    here = spread(0, 0)
    directions = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    near = min(spread(dy, dx) for dy, dx in directions)
    far = float(np.median([spread(ALIGN_FAR * dy, ALIGN_FAR * dx) for dy, dx in directions]))
    return bool(here <= ALIGNED_LOG_SPREAD and here <= ALIGN_NEAR_TOLERANCE * near and here <= ALIGN_FAR_FRACTION * far)


def _ratio_spread(
    log_dark: np.ndarray, log_bright: np.ndarray, dark_ok: np.ndarray, bright_ok: np.ndarray, dy: int, dx: int
) -> float:
    """Median absolute deviation of log(bright / dark) with the bright photo shifted by (dy, dx),
    over the same inner pixels at every shift up to ALIGN_FAR (inf when too few qualify)."""
    height, width = log_dark.shape
    inner = (slice(ALIGN_FAR, height - ALIGN_FAR), slice(ALIGN_FAR, width - ALIGN_FAR))
    moved = (slice(ALIGN_FAR + dy, height - ALIGN_FAR + dy), slice(ALIGN_FAR + dx, width - ALIGN_FAR + dx))
    shared = dark_ok[inner] & bright_ok[moved]
    if shared.sum() < MIN_SHARED_PIXELS:
        return math.inf
    ratios = log_bright[moved][shared] - log_dark[inner][shared]
    return float(np.median(np.abs(ratios - np.median(ratios))))


def aligned_members(images: list[np.ndarray], order: list[int], start: int, response: np.ndarray | None) -> list[int]:
    """The photos (indices into images) that line up with images[start], in `order`.

    order: indices from darkest to brightest. Walking out from `start` both ways, each next photo
    must line up with the last accepted one (`lines_up`); the walk stops at the first that does not.
    """
    position = order.index(start)
    kept = [start]
    for side, towards_dark in ((order[:position][::-1], True), (order[position + 1 :], False)):
        last = start
        for index in side:
            darker, brighter = (index, last) if towards_dark else (last, index)
            if not lines_up(images[darker], images[brighter], response):
                break
            kept.append(index)
            last = index
    return sorted(kept, key=order.index)


def estimate_relative_exposures(images: list[np.ndarray], response: np.ndarray | None, names: list[str]) -> list[float]:
    """Exposure of each photo relative to the darkest, for brackets whose exposure times are unknown.

    Photos are ordered by mean brightness. Each neighbour pair's ratio is sum(brighter) /
    sum(darker) of linearised pixels chosen on the brighter photo alone (well exposed there):
    choosing on the darker, noisier photo would favour pixels whose noise happened to be
    positive and bias the ratio low. Errors name the pair when too few pixels qualify.
    """
    order = brightness_order(images)
    relative = {order[0]: 1.0}
    for darker, brighter in zip(order, order[1:]):
        mask = (images[brighter] > WELL_EXPOSED[0]) & (images[brighter] < WELL_EXPOSED[1])
        a, b = linearise(images[darker], response)[mask], linearise(images[brighter], response)[mask]
        if len(a) < MIN_SHARED_PIXELS:
            raise DatasetError(
                f"{names[darker]}, {names[brighter]}: too few pixels are well exposed in "
                f"{names[brighter]} to tell the two exposures apart; give their exposure times "
                "with --exposure-csv"
            )
        ratio = float(b.sum() / max(a.sum(), 1e-12))
        relative[brighter] = relative[darker] * ratio
    return [relative[i] for i in range(len(images))]


def merge_bracket(
    images: list[np.ndarray], exposures: list[float], response: np.ndarray | None, names: list[str]
) -> np.ndarray:
    """Linear HDR float32 [H, W, 3], in units of linear exposure per unit of relative exposure.

    images: photos of one viewpoint, [H, W, 3] in [0, 1] (code values, or linear when response is
    None); exposures: their relative exposures. colour-hdri's weighted merge, row block by block.
    """
    check_exposures_differ(exposures, names)
    sizes = {image.shape for image in images}
    if len(sizes) > 1:
        raise DatasetError(f"{', '.join(names)}: the photos of this bracket differ in size ({sorted(sizes)})")
    from colour_hdri import image_stack_to_HDRI

    merge = partial(
        image_stack_to_HDRI,
        weighting_function=partial(merge_weights, response=response),
        camera_response_functions=None if response is None else np.asarray(response),
    )
    rows = []
    for top in range(0, images[0].shape[0], MERGE_ROWS):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # colour's notes on zero pixels: they are clipped to epsilon
            rows.append(merge(_stack([image[top : top + MERGE_ROWS] for image in images], exposures)))
    hdr = np.concatenate(rows).astype(np.float32)
    if not np.isfinite(hdr).all():
        raise DatasetError(f"{', '.join(names)}: the merge produced NaN or Inf; check the photos are not empty")
    return hdr


def dynamic_range_stops(hdr: np.ndarray, dark_percentile: float = 1.0) -> float:
    """log2 of the brightest luminance over a low percentile of the lit pixels' (noise-robust)."""
    luminance = hdr @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    lit = luminance[luminance > 0]
    if lit.size == 0:
        return 0.0
    return float(np.log2(luminance.max() / max(np.percentile(lit, dark_percentile), 1e-30)))
