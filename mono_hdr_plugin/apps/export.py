"""`mono-hdr export`: a trained model as files other tools open (layout: docs/exports.md).

3DGS: the standard 3DGS PLY that splat viewers read (the LDR Gaussians), and beside it the
method's HDR converters: OUT.converters.npz (weights) and OUT.converters.json (what they are,
how to apply them, the exposure model). Other backbones: a coloured point cloud PLY of the
surfaces their renders show (where the training views' rays terminate).
"""

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch
from rich.console import Console
from rich.progress import track
from torch import Tensor

from mono_hdr_plugin.apps.display import to_display, to_uint8
from mono_hdr_plugin.core.calibration import UNIT_TEXT
from mono_hdr_plugin.core.configs import config_from_dict
from mono_hdr_plugin.core.validation import FRACTION, POSITIVE, FlagError, at_least
from mono_hdr_plugin.data.io import atomic_path, read_ply_vertices, write_ply_vertices
from mono_hdr_plugin.methods.base import HdrMethod, build_method, method_config_for
from mono_hdr_plugin.training.evaluation import first_per_camera
from mono_hdr_plugin.training.trained import TrainedModel, load_trained_model

console = Console(stderr=True)
CONVERTERS_FORMAT = "mono-hdr-3d converters"
CONVERTERS_VERSION = 2  # 2: L2H-CC's weights signed per hidden unit (a non-decreasing converter)
POINT_CLOUD_HDR = ("hdr_red", "hdr_green", "hdr_blue")


@dataclass
class ExportConfig:
    """Export a checkpoint: 3DGS as a standard splat PLY with its HDR converters, others as a point cloud."""

    checkpoint: Path
    """A checkpoint written by `mono-hdr train`."""
    format: Literal["ply"] = "ply"
    """ply: Gaussian splats for 3DGS, a point cloud (x, y, z, red, green, blue, hdr_*) otherwise."""
    out: Path = Path("outputs/export/model.ply")
    """The PLY to write (3DGS also writes OUT.converters.npz and OUT.converters.json beside it)."""
    scale: float = 1.0
    """Point cloud: resolution of the rendered training views relative to the dataset's."""
    min_alpha: float = 0.5
    """Point cloud: keep pixels whose rays are at least this opaque."""
    max_points: int = 1_000_000
    """Point cloud: keep at most this many points (a random subset, seeded)."""

    flag_rules: ClassVar = {"scale": POSITIVE, "min_alpha": FRACTION, "max_points": at_least(1)}


def export_command(config: ExportConfig) -> None:
    if config.out.suffix.lower() != ".ply":  # --format ply: the suffix must agree (flag_rules cover the numbers)
        raise FlagError(f"--out must name a .ply file, got {config.out}")
    model = load_trained_model(config.checkpoint)
    if hasattr(model.pipeline.backbone, "export_ply"):
        written = export_splats(model, config.out)
    else:
        cloud = point_cloud(model, config.scale, config.min_alpha, config.max_points)
        written = [write_point_cloud(config.out, *cloud)]
        console.print(f"{cloud[0].shape[0]} points from {len(first_per_camera(model.scene.train))} training views")
    for path in written:
        console.print(f"wrote {path}")


def converters_paths(ply: Path) -> tuple[Path, Path]:
    """The weights (.npz) and description (.json) files that go with a splat PLY."""
    return ply.with_suffix(".converters.npz"), ply.with_suffix(".converters.json")


def export_splats(model: TrainedModel, path: Path) -> list[Path]:
    """The Gaussians as a 3DGS PLY, the method's converters beside it, and the backbone's environment map
    (`<name>.environment.exr`) or sky Gaussians (`<name>.sky.ply`) where it has them."""
    backbone: Any = model.pipeline.backbone  # export_command chose this path because it has export_ply
    backbone.export_ply(path)
    environment = [path.with_suffix(".environment.exr")] if getattr(backbone, "environment", None) is not None else []
    sky = [path.with_suffix(".sky.ply")] if getattr(backbone, "sky", None) is not None else []
    return [path, *save_converters(model, path), *environment, *sky]


def save_converters(model: TrainedModel, ply: Path) -> tuple[Path, Path]:
    """OUT.converters.npz: the method's weights by state-dict name (float32); OUT.converters.json:
    format, method and its config, the radiance calibration, the exposure model, and how to apply the weights."""
    weights_path, description_path = converters_paths(ply)
    method = model.pipeline.method
    arrays = {name: value.detach().float().numpy() for name, value in method.state_dict().items()}
    # np.savez on a path would append another .npz, so it writes to an open file
    with atomic_path(weights_path) as temporary, open(temporary, "wb") as handle:
        np.savez(handle, **arrays)
    description = {
        "format": CONVERTERS_FORMAT,
        "version": CONVERTERS_VERSION,
        "ply": ply.name,
        "weights": weights_path.name,
        "method": method.config.method,
        "method_config": asdict(method.config),
        "loss_kind": method.loss_kind,
        "hdr_recipe": method.hdr_recipe
        or f"the registered method {method.config.method!r}: apply its forward to "
        "the Gaussians' colours (see its documentation)",
        "radiance_calibration": model.pipeline.calibration.state(),
        "hdr_basis": model.pipeline.calibration.basis,
        "radiance": "calibrated HDR = radiance_calibration.scale * the recipe's hdr, in units of "
        + UNIT_TEXT[model.pipeline.calibration.units],
        "reference_exposure_seconds": model.exposure.reference_exposure,
        "display_scale": model.exposure.display_scale,
        "display": "at exposure t seconds a display shows srgb(display_scale * calibrated HDR * t / "
        "reference_exposure_seconds)",
        "arrays": {name: list(array.shape) for name, array in arrays.items()},
    }
    with atomic_path(description_path) as temporary:
        temporary.write_text(json.dumps(description, indent=2) + "\n")
    return weights_path, description_path


def load_converters(ply: Path) -> HdrMethod:
    """The method saved beside a splat PLY by save_converters, ready to render."""
    weights_path, description_path = converters_paths(Path(ply))
    for path in (weights_path, description_path):
        if not path.is_file():
            raise FileNotFoundError(f"no {path.name} beside {ply}: export the model again with `mono-hdr export`")
    description = json.loads(description_path.read_text())
    if description.get("format") != CONVERTERS_FORMAT or description.get("version") != CONVERTERS_VERSION:
        raise ValueError(f"{description_path} is not a version {CONVERTERS_VERSION} {CONVERTERS_FORMAT!r} file")
    method_config = description["method_config"]  # options nested, or flat as written before methods had their own
    method = build_method(
        config_from_dict(method_config_for(method_config["method"]), method_config), description["loss_kind"]
    )
    with np.load(weights_path) as arrays:
        method.load_state_dict({name: torch.from_numpy(arrays[name]) for name in arrays.files})
    return method.eval()


def points_from_depth(
    origins: Tensor, directions: Tensor, depth: Tensor, alpha: Tensor, min_alpha: float
) -> tuple[Tensor, Tensor]:
    """Where rays end: origin + (depth / alpha) * direction for rays at least `min_alpha` opaque.

    origins, directions [N, 3] (unit directions); depth [N] the expected distance along the ray
    (weights * t summed, so it shrinks with alpha) and alpha [N] the accumulated opacity.
    Returns the points [M, 3] and the indices [M] of the rays they came from.
    """
    kept = (alpha >= min_alpha).nonzero()[:, 0]
    distance = depth[kept] / alpha[kept].clamp_min(1e-6)
    return origins[kept] + distance[:, None] * directions[kept], kept


@torch.no_grad()
def point_cloud(
    model: TrainedModel, scale: float = 1.0, min_alpha: float = 0.5, max_points: int = 1_000_000
) -> tuple[Tensor, Tensor, Tensor]:
    """Points [N, 3], LDR colours [N, 3] in [0, 1] (the `ldr` output at the training exposure) and
    linear HDR [N, 3] where the training views' rays terminate."""
    points, colours, hdr = [], [], []
    views = first_per_camera(model.scene.train)
    for view in track(views, description="point cloud", console=console, transient=True):
        camera = view.camera.scaled(scale) if scale != 1 else view.camera
        frame = model.pipeline.render(camera, model.exposure.reference_exposure, with_depth=True)
        if frame.depth is None or frame.alpha is None:
            raise ValueError(
                f"the {model.pipeline.backbone_name!r} backbone renders no depth and opacity "
                "(LdrFeatures.extras 'depth' and 'alpha'), so there is no surface to export"
            )
        origins, directions = camera.rays()
        found, rays = points_from_depth(
            origins.reshape(-1, 3),
            directions.reshape(-1, 3),
            frame.depth.reshape(-1),
            frame.alpha.reshape(-1),
            min_alpha,
        )
        shown = to_display(frame, "ldr", model.exposure.reference_exposure, model.exposure).reshape(-1, 3)
        points.append(found)
        colours.append(shown[rays])
        hdr.append(frame.hdr.reshape(-1, 3)[rays])
    all_points, all_colours, all_hdr = torch.cat(points), torch.cat(colours), torch.cat(hdr)
    if all_points.shape[0] > max_points:
        keep = torch.randperm(all_points.shape[0], generator=torch.Generator().manual_seed(0))[:max_points]
        all_points, all_colours, all_hdr = all_points[keep], all_colours[keep], all_hdr[keep]
    return all_points, all_colours, all_hdr


def write_point_cloud(path: Path, points: Tensor, colours: Tensor, hdr: Tensor) -> Path:
    """A binary PLY point cloud: x, y, z (float), red, green, blue (uchar, what viewers show) and
    hdr_red, hdr_green, hdr_blue (float, linear radiance)."""
    names = [("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")] + [
        (name, "f4") for name in POINT_CLOUD_HDR
    ]
    vertices = np.empty(points.shape[0], dtype=names)
    rgb = to_uint8(colours)
    for index, axis in enumerate("xyz"):
        vertices[axis] = points[:, index].numpy()
    for index, name in enumerate(("red", "green", "blue")):
        vertices[name] = rgb[:, index]
    for index, name in enumerate(POINT_CLOUD_HDR):
        vertices[name] = hdr[:, index].float().numpy()
    return write_ply_vertices(path, vertices)


def load_point_cloud(path: Path) -> tuple[Tensor, Tensor, Tensor | None]:
    """A PLY point cloud: points [N, 3], colours [N, 3] in [0, 1] (grey when it has none) and the
    linear HDR [N, 3] written by write_point_cloud (None in other files)."""
    path = Path(path)
    vertex = read_ply_vertices(path, "point cloud")
    names = set(vertex.data.dtype.names)
    if not {"x", "y", "z"} <= names:
        raise ValueError(f"{path}: the vertices have no x, y, z")

    def columns(keys) -> Tensor:
        return torch.from_numpy(np.stack([np.asarray(vertex[key], dtype=np.float32) for key in keys], -1))

    points = columns("xyz")
    colours = (
        columns(("red", "green", "blue")) / 255.0 if {"red", "green", "blue"} <= names else torch.full_like(points, 0.5)
    )
    hdr = columns(POINT_CLOUD_HDR) if set(POINT_CLOUD_HDR) <= names else None
    return points, colours, hdr
