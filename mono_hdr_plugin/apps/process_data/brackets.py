"""Stage 4: bracket sets (photos of one viewpoint at several exposures, found from capture times and
recovered poses) planned and merged into linear HDR views (colour-hdri, data.photos.brackets); the
member as bright as the other photos is the set's LDR view."""

from dataclasses import dataclass

import numpy as np
from rich.console import Console
from rich.progress import track

from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig
from mono_hdr_plugin.apps.process_data.photos import StagedPhoto, photo_pixels
from mono_hdr_plugin.apps.process_data.records import HdrView, PhotoRecord
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.photos.brackets import (
    MIN_BRACKET_STOPS,
    BracketCandidate,
    UnreliableResponse,
    aligned_members,
    alignment_view,
    brightness_order,
    detect_brackets,
    estimate_relative_exposures,
    merge_bracket,
    recover_response,
    response_sample,
    spread_stops,
)
from mono_hdr_plugin.data.photos.raw import RawResponse, decode

RELIABLE_POINTS = 0.5
"""A photo's recovered pose is trusted for bracket detection when it sees this fraction of the
median photo's 3D points."""


@dataclass
class BracketPlan:
    """A set to merge: its photos (indices into the photo list) and their relative exposures."""

    members: list[int]
    exposures: list[float]
    estimated: bool
    view: int
    """The member whose LDR photo is the view: placed, and as bright as the capture's single photos."""


def find_bracket_plans(
    config: ProcessDataConfig, photos: list[PhotoRecord], staged: list[StagedPhoto], model, console: Console
) -> tuple[list[BracketPlan], list[str]]:
    """The bracket sets to merge and notes on members left out; none with --no-brackets or from a video."""
    if not config.brackets or config.video is not None:  # a video has no brackets; close frames are not one
        return [], []
    sets = detect_brackets(bracket_candidates(photos, staged, model), scene_scale(model), config.bracket)
    return plan_brackets(sets, photos, staged, config.raw_response, console)


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
    the median photo's 3D points are left out (such poses are placed off: docs/own_photos.md)."""
    placed = [image for image in model.images.values() if image.has_pose]
    enough = RELIABLE_POINTS * float(np.median([image.num_points3D for image in placed]))
    poses = {image.name: image for image in placed if image.num_points3D >= enough}
    candidates = []
    for photo, stage in zip(photos, staged):
        image = poses.get(photo.name)
        candidates.append(
            BracketCandidate(
                name=photo.source,
                exposure=photo.exposure,
                timestamp=stage.exif.timestamp,
                auto_bracket=stage.exif.auto_bracket,
                center=None if image is None else np.asarray(image.projection_center()),
                rotation=None if image is None else np.asarray(_cam_from_world(image).rotation.matrix()).T,
            )
        )
    return candidates


def _cam_from_world(image):
    pose = image.cam_from_world
    return pose() if callable(pose) else pose  # a method since pycolmap 3.12, a property before


def response_curve(name: RawResponse) -> np.ndarray:
    """[256, 3] linear value of each code value under a named response curve."""
    return np.stack([decode(np.linspace(0, 1, 256), name)] * 3, -1)


def plan_brackets(
    sets: list[list[int]],
    photos: list[PhotoRecord],
    staged: list[StagedPhoto],
    raw_response: RawResponse,
    console: Console,
) -> tuple[list[BracketPlan], list[str]]:
    """Bracket plans of the sets that have a placed photo, and notes on members left out.

    Members whose pixels do not line up with their neighbours' are left out (a placed one becomes
    a single view). Unknown exposure ratios are measured from the pixels. Both look at linear
    values: RAW photos are linear already, other photos go through the sRGB curve (what cameras
    encode with) until the camera's own response is recovered.
    """
    in_sets = {i for members in sets if len(members) > 1 for i in members}
    singles = [stage.brightness for i, stage in enumerate(staged) if i not in in_sets]
    typical = float(np.median(singles)) if singles else 0.5  # a set's view looks like the other photos
    plans, notes = [], []
    for members in track([m for m in sets if len(m) > 1], description="checking brackets", console=console):
        if not any(photos[i].registered for i in members):
            continue
        plan, dropped_note = plan_bracket(members, photos, staged, raw_response, typical)
        notes += dropped_note
        if plan is not None:
            plans.append(plan)
    return plans, notes


def plan_bracket(
    members: list[int], photos: list[PhotoRecord], staged: list[StagedPhoto], raw_response: RawResponse, typical: float
) -> tuple[BracketPlan | None, list[str]]:
    """The plan of one set with a placed member (None when what is left is no bracket: one photo, or
    exposures within MIN_BRACKET_STOPS), and notes naming the members left out.
    `typical`: the brightness the set's view should have."""
    placed = [k for k, i in enumerate(members) if photos[i].registered]
    names = [photos[i].source for i in members]
    if len({staged[i].raw for i in members}) > 1:
        raise DatasetError(
            f"{', '.join(names)}: this bracket mixes RAW and JPEG/PNG/TIFF photos; shoot the "
            "bracket in one format, or pass --no-brackets"
        )
    response = None if staged[members[0]].raw else response_curve("srgb")
    samples, views = [], []
    for i in members:
        encoded, linear = photo_pixels(staged[i], raw_response)
        samples.append(response_sample(encoded if linear is None else linear))
        views.append(alignment_view(encoded if linear is None else linear))
    known = photos[members[0]].exposure is not None
    times = [time for time in (photos[i].exposure for i in members) if time is not None]
    assert not known or len(times) == len(members)  # assign_exposures gives all photos a time or none
    order = sorted(range(len(members)), key=lambda k: times[k]) if known else brightness_order(samples)
    start = min(placed, key=lambda k: abs(order.index(k) - len(order) // 2))
    kept = aligned_members(views, order, start, response)
    dropped = [names[k] for k in range(len(members)) if k not in kept]
    notes = (
        [
            f"{', '.join(dropped)}: do not line up with the other photos of their bracket "
            f"({', '.join(names[k] for k in kept)}) and are left out of its merge"
        ]
        if dropped
        else []
    )
    if len(kept) < 2:
        return None, [
            f"{', '.join(names)}: taken as one viewpoint, but their pixels do not line up in place (another "
            "viewpoint, or something moved): not merged"
        ]
    if known:
        exposures = [times[k] for k in kept]
    else:
        exposures = estimate_relative_exposures([samples[k] for k in kept], response, [names[k] for k in kept])
    if spread_stops(exposures) < MIN_BRACKET_STOPS:
        kept_names = ", ".join(names[k] for k in kept)
        return None, notes + [
            f"{kept_names}: one viewpoint, but their exposures span only {spread_stops(exposures):.2f} stops "
            f"(a bracket needs {MIN_BRACKET_STOPS:.2f}): kept as single photos, not merged"
        ]
    view = min((k for k in kept if k in placed), key=lambda k: abs(staged[members[k]].brightness - typical))
    return BracketPlan(
        members=[members[k] for k in kept], exposures=exposures, estimated=not known, view=members[view]
    ), notes


def bracket_response(
    plans: list[BracketPlan], staged: list[StagedPhoto], raw_response: RawResponse, console: Console
) -> tuple[np.ndarray | None, str | None, list[str]]:
    """The camera response [256, 3] of the JPEG brackets (Debevec), or of the RAW photos' chosen
    curve; what it is; a note when the brackets could not carry a response and sRGB was used."""
    coded = [plan for plan in plans if not staged[plan.members[0]].raw]
    if coded:
        samples = []
        for plan in track(coded, description="recovering the camera response", console=console):
            images = [response_sample(photo_pixels(staged[i], raw_response)[0]) for i in plan.members]
            samples.append((images, plan.exposures))
        try:
            return recover_response(samples), f"recovered from {len(coded)} bracket set(s) (Debevec & Malik 1997)", []
        except UnreliableResponse as reason:
            note = (
                f"camera response not fitted ({reason}): the merges and training use the sRGB curve; for a "
                "fitted one shoot brackets of 3 or more exposures 1-3 stops apart of a view with dark and "
                "bright parts"
            )
            return response_curve("srgb"), "srgb (default: the brackets could not carry a fitted response)", [note]
    if any(stage.raw for stage in staged):
        return response_curve(raw_response), f"{raw_response} (RAW photos)", []
    return None, None, []


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
        hdr_views.append(
            HdrView(
                name=photos[plan.view].name,
                sources=[photos[i].source for i in plan.members],
                exposures=list(plan.exposures),
                exposures_estimated=plan.estimated,
            )
        )
    return hdr_views


def merge_plan(
    plan: BracketPlan,
    staged: list[StagedPhoto],
    response: np.ndarray | None,
    raw_response: RawResponse,
    sources: list[str],
) -> np.ndarray:
    """The linear HDR [H, W, 3] of one planned set: RAW members merge their linear pixels (no response
    needed), the others their code values through the camera `response`."""
    pixels = [photo_pixels(staged[i], raw_response) for i in plan.members]
    images = [linear if linear is not None else encoded for encoded, linear in pixels]
    darkest = min(plan.exposures)
    return merge_bracket(
        images, [e / darkest for e in plan.exposures], None if staged[plan.members[0]].raw else response, sources
    )
