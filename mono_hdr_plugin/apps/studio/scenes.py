"""The built-in scenes. Each exercises something different; all exceed 1e4 : 1 dynamic range.
The outdoor ones (open sky and sun) are defined in outdoor.py."""

from typing import TypedDict

import numpy as np

from mono_hdr_plugin.apps.studio.capture import CaptureSettings
from mono_hdr_plugin.apps.studio.outdoor import OUTDOOR_SCENES
from mono_hdr_plugin.apps.studio.scene import (
    CameraRig,
    StudioScene,
    box,
    checker,
    diffuse,
    lamp,
    look_at_matrix,
    noise_texture,
    panel,
    place,
    projector,
    rgb,
    rotate,
    scale,
    translate,
)

WINDOW = (-0.7, 0.7, 0.9, 1.9)
"""x0, x1, z0, z1 of the window hole in the +y wall of the room."""


def _room(size: float = 2.0, height: float = 2.5, window: bool = False, albedo: float = 0.55) -> dict:
    """Floor, ceiling and four walls facing inwards; the +y wall optionally has a window hole."""
    wall = diffuse(rgb(albedo, albedo * 0.95, albedo * 0.87))
    room = {
        "floor": panel(scale(size), diffuse(checker(rgb(0.45, 0.3, 0.18), rgb(0.2, 0.12, 0.07), 8))),
        "ceiling": panel(place(translate(0, 0, height), rotate("x", 180), scale(size)), wall),
        "wall_left": panel(place(translate(-size, 0, height / 2), rotate("y", 90), scale(height / 2, size, 1)), wall),
        "wall_right": panel(place(translate(size, 0, height / 2), rotate("y", -90), scale(height / 2, size, 1)), wall),
        "wall_front": panel(place(translate(0, -size, height / 2), rotate("x", -90), scale(size, height / 2, 1)), wall),
    }
    back = place(translate(0, size, 0), rotate("x", 90))  # local xy plane = the back wall
    if not window:
        room["wall_back"] = panel(place(back, translate(0, height / 2, 0), scale(size, height / 2, 1)), wall)
        return room
    x0, x1, z0, z1 = WINDOW
    pieces = {
        "below": (-size, size, 0.0, z0),
        "above": (-size, size, z1, height),
        "left": (-size, x0, z0, z1),
        "right": (x1, size, z0, z1),
    }
    for name, (x0, x1, z0, z1) in pieces.items():
        room[f"wall_back_{name}"] = panel(
            place(back, translate((x0 + x1) / 2, (z0 + z1) / 2, 0), scale((x1 - x0) / 2, (z1 - z0) / 2, 1)), wall
        )
    return room


def demo_content() -> dict:
    """Checkered floor and wall, three coloured objects, one bright bulb in the dark: small and fast."""
    return {
        "floor": panel(scale(2.0), diffuse(checker(rgb(0.8, 0.78, 0.7), rgb(0.12, 0.16, 0.3), 10))),
        "wall": panel(
            place(translate(0, 1.2, 1.0), rotate("x", 90), scale(2.0, 1.0, 1)),
            diffuse(checker(rgb(0.75, 0.25, 0.2), rgb(0.9, 0.85, 0.6), 6)),
        ),
        "red_box": box((-0.6, 0.1, 0.25), (0.5, 0.5, 0.5), diffuse(rgb(0.7, 0.1, 0.08))),
        "green_ball": {
            "type": "sphere",
            "center": [0.25, -0.2, 0.3],
            "radius": 0.3,
            "bsdf": diffuse(checker(rgb(0.1, 0.6, 0.15), rgb(0.9, 0.9, 0.9), 6)),
        },
        "blue_pillar": box((0.8, 0.5, 0.45), (0.3, 0.3, 0.9), diffuse(rgb(0.1, 0.2, 0.7))),
        "bulb": lamp((-0.1, 0.7, 1.25), 0.07, (3000.0, 2700.0, 2200.0)),
    }


def textured_desk_content() -> dict:
    """The demo's layout with textures that never repeat and a dimmer, larger bulb: a scene a
    photographer can capture whole (structure from motion places every photo; a bracket reaches
    below the bulb's white), for the own-photos pipeline and its benchmark."""
    return {
        "floor": panel(scale(2.0), diffuse(noise_texture(1))),
        "wall": panel(
            place(translate(0, 1.2, 1.0), rotate("x", 90), scale(2.0, 1.0, 1)), diffuse(noise_texture(2, tiles=0.7))
        ),
        "crate": box((-0.6, 0.1, 0.25), (0.5, 0.5, 0.5), diffuse(noise_texture(3, tiles=0.5))),
        "ball": {
            "type": "sphere",
            "center": [0.25, -0.2, 0.3],
            "radius": 0.3,
            "bsdf": diffuse(noise_texture(4, tiles=2.0)),
        },
        "pillar": box((0.8, 0.5, 0.45), (0.3, 0.3, 0.9), diffuse(noise_texture(5, tiles=0.5))),
        "bulb": lamp((-0.1, 0.7, 1.25), 0.1, (400.0, 360.0, 300.0)),
    }


def lamp_room_content() -> dict:
    """A closed room lit only by a visible floor-lamp bulb; table, sofa and a picture."""
    return {
        **_room(),
        "table": box((0.2, 0.6, 0.4), (1.0, 0.6, 0.08), diffuse(rgb(0.35, 0.22, 0.12))),
        "table_leg": box((0.2, 0.6, 0.18), (0.1, 0.1, 0.36), diffuse(rgb(0.2, 0.12, 0.07))),
        "sofa": box((-1.2, 1.3, 0.25), (1.2, 0.6, 0.5), diffuse(rgb(0.15, 0.25, 0.45))),
        "sofa_back": box((-1.2, 1.7, 0.55), (1.2, 0.2, 0.6), diffuse(rgb(0.12, 0.2, 0.4))),
        "picture": panel(
            place(translate(0.3, 1.99, 1.4), rotate("x", 90), scale(0.5, 0.35, 1)),
            diffuse(checker(rgb(0.8, 0.7, 0.2), rgb(0.1, 0.3, 0.5), 4)),
        ),
        "lamp_pole": box((1.3, 1.3, 0.7), (0.05, 0.05, 1.4), diffuse(rgb(0.05))),
        "bulb": lamp((1.3, 1.3, 1.5), 0.1, (4000.0, 3200.0, 2200.0)),
    }


def sunlit_window_content() -> dict:
    """A dark room whose only light is a bright sky and the sun through one window.

    Every light is a point source, which a path tracer samples exactly: the sun patch comes from
    a projector just inside the window aimed along the sun's direction, the sky's light from a
    wider, dimmer blue projector beside it (both with soft edges, as the sun's disc gives), and
    the sky seen through the window is a white board outside lit by a spot that faces away from
    the room. A large emitting panel in the window would light the room the same way but take
    ~100x the samples to converge.
    """
    x0, x1, z0, z1 = WINDOW
    middle = np.array([(x0 + x1) / 2, 1.98, (z0 + z1) / 2])
    sun = np.array([0.2, -1.0, -1.0])
    return {
        **_room(window=True, albedo=0.15),
        "cabinet": box((-1.3, -1.3, 0.5), (0.6, 0.6, 1.0), diffuse(rgb(0.08, 0.06, 0.05))),
        "armchair": box((1.0, 0.2, 0.3), (0.7, 0.7, 0.6), diffuse(checker(rgb(0.5, 0.1, 0.1), rgb(0.1), 3))),
        "rug": panel(
            place(translate(-0.2, 0.4, 0.005), scale(0.8, 0.6, 1)),
            diffuse(checker(rgb(0.1, 0.3, 0.35), rgb(0.6, 0.55, 0.3), 5)),
        ),
        "sky": panel(
            place(
                translate(0, 3.2, 0), rotate("x", 90), translate((x0 + x1) / 2, (z0 + z1) / 2, 0), scale(3.0, 2.5, 1)
            ),
            diffuse(rgb(0.8)),
        ),
        "sky_light": {
            "type": "spot",
            "cutoff_angle": 70.0,
            "beam_width": 45.0,
            "intensity": rgb(150.0, 180.0, 230.0),
            "to_world": look_at_matrix(middle + [0, 0.07, 0], middle + [0, 1.0, 0], (0.0, 0.0, 1.0)),
        },
        "sun": projector(
            middle,
            middle + sun,
            (0.0, 0.0, 1.0),
            24.0,
            (4000.0, 3800.0, 3300.0),
            aspect=(x1 - x0) / (z1 - z0),
            soft_edge=0.12,
        ),
        "skylight": projector(
            middle, middle + np.array([0.0, -1.0, -0.6]), (0.0, 0.0, 1.0), 100.0, (15.0, 18.0, 23.0), soft_edge=0.25
        ),
    }


def glossy_content() -> dict:
    """Metal and plastic spheres under one small, very bright light: specular highlights."""
    return {
        "floor": panel(scale(3.0), diffuse(checker(rgb(0.6), rgb(0.05), 12))),
        "gold": {
            "type": "sphere",
            "center": [-0.7, 0.0, 0.35],
            "radius": 0.35,
            "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.15},
        },
        "mirror": {
            "type": "sphere",
            "center": [0.1, 0.4, 0.35],
            "radius": 0.35,
            "bsdf": {"type": "conductor", "material": "Al"},
        },
        "plastic": {
            "type": "sphere",
            "center": [0.75, -0.3, 0.3],
            "radius": 0.3,
            "bsdf": {"type": "roughplastic", "alpha": 0.05, "diffuse_reflectance": rgb(0.1, 0.25, 0.7)},
        },
        "copper_box": box(
            (0.0, -0.6, 0.15), (0.4, 0.4, 0.3), {"type": "roughconductor", "material": "Cu", "alpha": 0.2}
        ),
        "spot": lamp((0.4, 0.8, 1.6), 0.06, (20000.0, 19000.0, 17000.0)),
        "fill": {"type": "point", "position": [-1.8, -1.6, 2.2], "intensity": rgb(12.0, 13.0, 15.0)},
    }


def coloured_light_content() -> dict:
    """White objects in a corner lit by a red and a blue bulb: coloured light, coloured shadows."""
    white = diffuse(rgb(0.8))
    return {
        "floor": panel(scale(2.5), diffuse(checker(rgb(0.8), rgb(0.4), 10))),
        "wall_back": panel(place(translate(0, 1.5, 1.25), rotate("x", 90), scale(2.5, 1.25, 1)), white),
        "wall_left": panel(place(translate(-1.5, 0.3, 1.25), rotate("y", 90), scale(1.25, 1.2, 1)), white),
        "cube": box((-0.3, 0.4, 0.3), (0.6, 0.6, 0.6), white),
        "ball": {"type": "sphere", "center": [0.5, -0.1, 0.35], "radius": 0.35, "bsdf": white},
        "column": box((-0.9, 0.9, 0.6), (0.3, 0.3, 1.2), white),
        "red_bulb": lamp((-0.9, -0.3, 1.1), 0.035, (20000.0, 1200.0, 600.0)),
        "blue_bulb": lamp((0.9, 0.8, 1.3), 0.035, (600.0, 2400.0, 24000.0)),
    }


class ArcAngles(TypedDict):
    """The camera arc of a CameraRig, passed as keyword arguments."""

    azimuth_deg: tuple[float, float]
    elevation_deg: tuple[float, float]


FORWARD_ARC = ArcAngles(azimuth_deg=(-120.0, -60.0), elevation_deg=(12.0, 30.0))

BUILTIN_SCENES = (
    StudioScene(
        name="demo",
        description="small fast scene: checkered floor and wall, three objects, a bulb",
        content=demo_content,
        rig=CameraRig(target=(0.0, 0.3, 0.5), radius=3.6, fov_deg=50, **FORWARD_ARC),
        spp=121,
        effects=("exposure", "crf", "clip", "quantize"),
    ),
    StudioScene(
        name="lamp-room",
        description="room lit by one visible floor-lamp bulb",
        content=lamp_room_content,
        rig=CameraRig(
            target=(0.2, 1.0, 0.9), radius=2.4, azimuth_deg=(-125.0, -55.0), elevation_deg=(5.0, 20.0), fov_deg=70
        ),
        effects=("exposure", "noise", "vignette", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="srgb", vignette=0.25, full_well=4000.0),
    ),
    StudioScene(
        name="sunlit-window",
        description="dark interior, bright sky and a sun patch through a window",
        content=sunlit_window_content,
        rig=CameraRig(
            target=(0.0, 1.5, 1.1), radius=3.0, azimuth_deg=(-115.0, -65.0), elevation_deg=(2.0, 15.0), fov_deg=75
        ),
        spp=361,
        effects=("exposure", "gain", "offset", "noise", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="film", gain=1.5, offset=0.004, read_noise=0.003),
    ),
    StudioScene(
        name="glossy",
        description="gold, mirror and plastic spheres with sharp highlights",
        content=glossy_content,
        rig=CameraRig(
            target=(0.0, 0.0, 0.3), radius=3.2, azimuth_deg=(-180.0, 0.0), elevation_deg=(15.0, 40.0), fov_deg=45
        ),
        effects=("exposure", "white_balance", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="gamma", gamma=2.2, white_balance=(1.08, 1.0, 0.92), bits=12),
    ),
    StudioScene(
        name="coloured-light",
        description="white objects under a red and a blue bulb",
        content=coloured_light_content,
        rig=CameraRig(target=(0.0, 0.4, 0.6), radius=3.4, fov_deg=55, **FORWARD_ARC),
        effects=("exposure", "vignette", "white_balance", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="bt709", vignette=0.2, white_balance=(0.95, 1.0, 1.1)),
    ),
    StudioScene(
        name="textured-desk",
        description="the demo's layout with non-repeating textures: for photographing it",
        content=textured_desk_content,
        rig=CameraRig(target=(0.0, 0.3, 0.5), radius=3.6, fov_deg=50, **FORWARD_ARC),
        spp=121,
        effects=("exposure", "noise", "crf", "clip", "quantize"),
        capture=CaptureSettings(crf="srgb"),
    ),
    *OUTDOOR_SCENES,
)

SCENES: dict[str, StudioScene] = {scene.name: scene for scene in BUILTIN_SCENES}
