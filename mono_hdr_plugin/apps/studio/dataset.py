"""A studio scene as a dataset: render once (cached), photograph every view at t1..t5."""

from dataclasses import replace

import numpy as np
import torch

from mono_hdr_plugin.apps.studio.capture import capture, inverse_response_curve
from mono_hdr_plugin.apps.studio.render import SceneRender, render_scene
from mono_hdr_plugin.apps.studio.scene import StudioScene
from mono_hdr_plugin.apps.studio.scenes import SCENES
from mono_hdr_plugin.core.camera_optimizer import EXACT
from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot, bounds_from_points, constant
from mono_hdr_plugin.data.errors import DatasetError

MAX_INIT_POINTS = 10_000


def get_scene(name: str, resolution: int | None = None) -> StudioScene:
    """The built-in scene called `name`, at `resolution` x `resolution` pixels if given (the cameras keep
    their field of view: the focal length scales with the image; the render cache keeps each size apart)."""
    if name not in SCENES:
        raise DatasetError(f"unknown scene {name!r}; choose one of {sorted(SCENES)} (mono-hdr scenes)")
    scene = SCENES[name]
    return scene if resolution is None else replace(scene, resolution=(resolution, resolution))


def photo_seed(seed: int, view: int, exposure_index: int) -> int:
    """Noise seed of one photo: the same photo gets the same noise whatever the protocol."""
    return int(np.random.SeedSequence([seed, view, exposure_index]).generate_state(1)[0])


def _photo(render: SceneRender, scene: StudioScene, view: int, exposure_index: int, seed: int):
    exposure = scene.exposures[exposure_index]
    return lambda: capture(
        render.radiance[view], exposure, scene.effects, scene.capture, seed=photo_seed(seed, view, exposure_index)
    )


SKY_FAR_OVER_NEAR = 1000.0
"""far / near of a view that sees the sky. Its sky pixels lie at infinity, which no finite far
reaches (Camera needs one); at 1000x near, a sampler linear in disparity has covered 99.9 % of
the disparity range from near to infinity, and the backbones draw what lies beyond as background."""


def _cameras_with_depth_range(scene: StudioScene, render: SceneRender, unbounded: bool) -> list[Camera]:
    """Scene cameras with near/far set from the surfaces each one sees (and the sky, if it sees it)."""
    cameras = []
    for camera, positions, hit in zip(scene.cameras(), render.positions, render.hit):
        distances = np.linalg.norm(positions[hit] - camera.center.numpy(), axis=-1)
        near, far = 0.8 * distances.min(), 1.2 * distances.max()
        if unbounded and not hit.all():  # a pixel that misses every surface sees the sky
            far = max(far, SKY_FAR_OVER_NEAR * near)
        cameras.append(replace(camera, near=float(near), far=float(far)))
    return cameras


def _initial_points(scene: StudioScene, render: SceneRender, views: list[CapturedView]):
    """Surface points seen by the train views, coloured by their middle-exposure photos.

    The same kind of points structure-from-motion gives a real capture: none in the sky.
    """
    rng = np.random.default_rng(0)
    seen_points, seen_colours = [], []
    for view in views:
        if view.split != "train":
            continue
        hit = render.hit[view.view_id]
        seen_points.append(render.positions[view.view_id][hit])
        seen_colours.append(view.shots[len(view.shots) // 2].image()[hit])
    points, colours = np.concatenate(seen_points), np.concatenate(seen_colours)
    keep = rng.choice(len(points), min(MAX_INIT_POINTS, len(points)), replace=False)
    return torch.from_numpy(points[keep]).float(), torch.from_numpy(colours[keep]).float()


def studio_captured_scene(scene: StudioScene, seed: int = 0) -> CapturedScene:
    """Render `scene` (or read the cached render) and photograph each view at every exposure."""
    render = render_scene(scene)
    unbounded = scene.unbounded()
    views = [
        CapturedView(
            view_id=index,
            camera=camera,
            split=scene.split(index),
            name=f"{index:03d}",
            shots=[
                Shot(exposure, _photo(render, scene, index, e, seed), f"{index:03d}_{e}")
                for e, exposure in enumerate(scene.exposures)
            ],
            hdr=constant(render.radiance[index]),
        )
        for index, camera in enumerate(_cameras_with_depth_range(scene, render, unbounded))
    ]
    bounds_min, bounds_max = bounds_from_points(render.positions[render.hit])
    points, colours = _initial_points(scene, render, views)
    return CapturedScene(
        name=scene.name,
        views=views,
        bounds_min=bounds_min,
        bounds_max=bounds_max,
        points=points,
        point_colors=colours,
        metadata={
            "source": "studio",
            "poses": EXACT,
            "effects": scene.effects,
            "exposures": scene.exposures,
            "unbounded": unbounded,
            "camera_response": capture_response(scene).tolist(),
            "camera_response_source": f"of the studio's capture ({capture_curve_name(scene)})",
        },
    )


def capture_response(scene: StudioScene) -> np.ndarray:
    """The response table [256, 3] (code value k / 255 -> linear exposure) of the scene's camera: its
    curve where the scene declares one (`crf` among its effects), else linear. What a user who knows
    the camera would give: the HDR prior and the calibration then linearise photos as they were made."""
    code = np.linspace(0.0, 1.0, 256)
    linear = inverse_response_curve(code, scene.capture).astype(np.float64) if "crf" in scene.effects else code
    return np.stack([linear] * 3, -1)


def capture_curve_name(scene: StudioScene) -> str:
    return f"{scene.capture.crf} curve" if "crf" in scene.effects else "linear"
