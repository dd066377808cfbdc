"""The one entry point from a DataConfig to a SceneData: files on disk or a studio scene."""

import warnings
from dataclasses import replace
from pathlib import PurePosixPath

import numpy as np
import torch

from mono_hdr_plugin.core.cameras import Camera
from mono_hdr_plugin.core.validation import FlagError, check_flags
from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import SceneData, View, check_hdr_ground_truth, warn_uninformative_hdr
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.extent import decide_extent
from mono_hdr_plugin.data.layouts import read_layout
from mono_hdr_plugin.data.protocols import select_shots
from mono_hdr_plugin.data.sources import named_scene, scene_names


def captured_scene(config: DataConfig) -> CapturedScene:
    """Every photo of the scene that `config` names (--data folder or --scene name)."""
    if config.data is not None and config.scene is not None:
        raise FlagError(f"--data {config.data} and --scene {config.scene} name two scenes: pass one of them")
    if config.data is not None:
        if config.resolution is not None:
            raise FlagError(
                f"--resolution {config.resolution} sizes a --scene; the photos in --data {config.data} keep "
                "their size: shrink them with --downscale"
            )
        return read_layout(config.data, config.layout)
    if config.scene is not None:
        return named_scene(config.scene, seed=config.exposure_seed, resolution=config.resolution)
    raise DatasetError(
        f"no scene given: pass --data FOLDER or --scene NAME (built-in scenes: {', '.join(scene_names())})"
    )


def downscale_image(image: np.ndarray, factor: int, label: str) -> np.ndarray:
    """Average `factor` x `factor` pixel blocks (area resampling); the remainder is cropped."""
    if factor == 1:
        return image
    height, width = image.shape[0] // factor, image.shape[1] // factor
    if height == 0 or width == 0:
        raise DatasetError(
            f"{label}: image {image.shape[1]}x{image.shape[0]} is smaller than "
            f"--downscale {factor}; use a smaller factor"
        )
    blocks = image[: height * factor, : width * factor].reshape(height, factor, width, factor, 3)
    return blocks.mean(axis=(1, 3), dtype=np.float32)


def downscaled_shot(shot: Shot, camera: Camera, factor: int) -> tuple[np.ndarray, Camera]:
    """The photo downscaled by `factor` and its camera (`camera` is downscaled_camera's): the smaller copy
    the dataset stores, if any, at its own size (it may round where the area average crops: 4946 px / 4
    is 1237 in Mip-NeRF 360's images_4), else the area average."""
    if factor in shot.downscaled:
        pixels = shot.downscaled[factor]()
        return pixels, replace(camera, width=pixels.shape[1], height=pixels.shape[0])
    return downscale_image(shot.image(), factor, shot.name), camera


def downscaled_camera(camera: Camera, factor: int) -> Camera:
    """The camera of an image downscaled by `factor` (downscale_image): focal lengths and principal point
    divided by `factor`, the size the whole blocks (the remainder is cropped at the right and bottom)."""
    if factor == 1:
        return camera
    return replace(camera.scaled(1.0 / factor), width=camera.width // factor, height=camera.height // factor)


def _views(view: CapturedView, shots: list[Shot], factor: int, levels: list[float], notes: list[str]) -> list[View]:
    """The views of the chosen shots; HDR ground truth that carries no HDR information is left out
    (with a note naming its file), negative HDR ground truth refused."""
    camera = downscaled_camera(view.camera, factor)
    hdr = None
    if view.hdr is not None:
        label = str(getattr(view.hdr, "path", view.name))
        pixels = view.hdr()
        if pixels.shape[:2] != (view.camera.height, view.camera.width):  # named here: View would name the photo
            raise DatasetError(
                f"{label}: HDR ground truth is {pixels.shape[1]}x{pixels.shape[0]} but the photos of view "
                f"{view.name or view.view_id} are {view.camera.width}x{view.camera.height}; export it at the "
                "photos' size"
            )
        reason = check_hdr_ground_truth(pixels, label)
        if reason:
            notes.append(f"{label} {reason}")
        else:
            hdr = torch.from_numpy(downscale_image(pixels, factor, label))
    token = PurePosixPath(view.name).name or f"{view.view_id:03d}"
    views = []
    for shot in shots:
        pixels, shot_camera = downscaled_shot(shot, camera, factor)
        views.append(
            View(
                camera=shot_camera,
                image=torch.from_numpy(pixels),
                exposure=float(shot.exposure),
                view_id=view.view_id,
                name=shot.name,
                hdr=hdr,
                stem=f"{token}_t{exposure_level(levels, shot.exposure)}",
            )
        )
    return views


def exposure_level(levels: list[float], exposure: float) -> int:
    """1-based index of `exposure` among the scene's exposure levels (t1, t2, ...)."""
    return 1 + int(np.argmin(np.abs(np.log(np.asarray(levels)) - np.log(exposure))))


def check_same_size(scene: CapturedScene, views: list[View]) -> None:
    """Every image of a scene must have one size: a backbone renders one image size."""
    sizes = {(v.camera.width, v.camera.height) for v in views}
    if len(sizes) > 1:
        examples = {size: next(v.name for v in views if (v.camera.width, v.camera.height) == size) for size in sizes}
        listing = ", ".join(f"{name} is {w}x{h}" for (w, h), name in examples.items())
        raise DatasetError(
            f"scene {scene.name!r} mixes image sizes ({listing}); resize all images "
            "to one size (and scale the intrinsics with them)"
        )


def warn_partial_hdr(scene: CapturedScene) -> None:
    """Some views with HDR ground truth and some without is almost always a missing EXR file: say which
    (unless the layout says so by design: a process-data capture has HDR at its bracketed views only)."""
    if scene.metadata.get("partial_hdr_expected"):
        return
    lacking = [view.name or str(view.view_id) for view in scene.views if view.hdr is None]
    if 0 < len(lacking) < len(scene.views):
        listing = ", ".join(lacking[:5]) + (f" and {len(lacking) - 5} more" if len(lacking) > 5 else "")
        warnings.warn(
            f"scene {scene.name!r} ({scene.metadata.get('source', 'in memory')}): {len(lacking)} of "
            f"{len(scene.views)} views have no HDR ground truth ({listing}); they get no HDR loss "
            "and no HDR metrics. Add their EXR files if they were meant to have them.",
            stacklevel=2,
        )


def check_image_sizes(scene: CapturedScene, factor: int, min_side: int) -> None:
    """After --downscale `factor`, every image must keep `min_side` pixels a side. Checked on the cameras
    before a photo is decoded; the error names the smallest image and the largest factor that works."""
    smallest = min(scene.views, key=lambda view: min(view.camera.width, view.camera.height))
    side = min(smallest.camera.width, smallest.camera.height)
    if side // factor >= min_side:
        return
    name = smallest.name or f"view {smallest.view_id}"
    image = f"{name} of scene {scene.name!r} ({smallest.camera.width}x{smallest.camera.height})"
    if side < min_side:
        raise DatasetError(f"{image} is under the {min_side} pixels a side this command needs; use larger images")
    raise FlagError(
        f"--downscale {factor} leaves {image} under {min_side} pixel{'s' if min_side > 1 else ''} a side; "
        f"the largest factor that works is {side // min_side}"
    )


def scene_extent(metadata: dict, train: list[View], config: DataConfig) -> tuple[bool, str]:
    """Whether the scene is unbounded, and why: --extent when forced, a studio scene's content, else the
    training photos (data/extent.py); metadata that claims otherwise is named and overruled."""
    if config.extent != "auto":
        return config.extent == "unbounded", f"{config.extent} (--extent {config.extent})"
    if metadata.get("source") == "studio":  # its content has a sky emitter or not
        if metadata["unbounded"]:
            return True, "unbounded: the studio scene has a sky emitter"
        return False, "bounded: the studio scene has no sky emitter"
    decision = decide_extent([view.image for view in train], [view.camera for view in train])
    reason = decision.reason
    declared = metadata.get("declared_unbounded")
    if declared is not None and declared != decision.unbounded:
        claim = "unbounded (aabb_scale > 1)" if declared else "bounded (aabb_scale <= 1)"
        reason += f"; the transforms file declares it {claim}, overruled: force it with --extent"
    return decision.unbounded, reason


def to_scene_data(scene: CapturedScene, config: DataConfig, min_side: int = 1) -> SceneData:
    """Apply the exposure protocol and --downscale; decode only the chosen photos. `min_side`: the fewest
    pixels a side the caller can use (training and evaluation: SSIM's window)."""
    check_flags(config)
    check_image_sizes(scene, config.downscale, min_side)
    warn_partial_hdr(scene)
    chosen = select_shots(scene, config)
    splits: dict[str, list[View]] = {"train": [], "test": []}
    notes: list[str] = []
    for view in scene.views:
        splits[view.split].extend(_views(view, chosen[id(view)], config.downscale, scene.exposure_levels, notes))
    if notes:
        warn_uninformative_hdr(scene.name, notes)
    check_same_size(scene, splits["train"] + splits["test"])
    metadata = {**scene.metadata, "protocol": config.protocol, "exposure_levels": scene.exposure_levels}
    metadata["unbounded"], metadata["extent_reason"] = scene_extent(metadata, splits["train"], config)
    return SceneData(
        name=scene.name,
        train=splits["train"],
        test=splits["test"],
        bounds_min=scene.bounds_min,
        bounds_max=scene.bounds_max,
        points=scene.points,
        point_colors=scene.point_colors,
        metadata=metadata,
    )


def load_scene(config: DataConfig, min_side: int = 1) -> SceneData:
    """Load the scene `config` names under its exposure protocol: the one call trainers make (with
    `min_side`, to_scene_data's)."""
    return to_scene_data(captured_scene(config), config, min_side)
