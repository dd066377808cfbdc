"""Synthetic scenes and tiny backbone configs for the hard-case tests (no Mitsuba, seconds).

Every scene is a small orbit of cameras around the box [-1, 1]^3; the HDR ground truth of a
view is a smooth analytic radiance pattern, and its LDR photo is the imaging equation
(exposure, clip, gamma, 8-bit quantisation) applied to it. Tests bend the HDR values or the
exposures to reach a hard case.
"""

import math
from pathlib import Path

import torch
from helpers import quiet_config
from register_backbone import VoxelGridConfig  # examples/, on sys.path via tests/conftest.py
from torch import Tensor

from backbones.gs import DefaultStrategy, GaussianConfig
from backbones.nerf import GridFieldConfig, MlpFieldConfig, NerfConfig
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.data.dataset import SceneData, View
from mono_hdr_plugin.training.trainer import Trainer

BACKBONES = ("voxel-grid", "gs", "nerf")
BOUNDS = (-torch.ones(3), torch.ones(3))


def orbit_camera(
    index: int, count: int, size: int, radius: float = 3.0, height: float = 0.8, near: float = 1.0, far: float = 5.0
) -> Camera:
    angle = 2 * math.pi * index / count
    eye = torch.tensor([radius * math.cos(angle), radius * math.sin(angle), height])
    return Camera(
        look_at(eye, torch.zeros(3)),
        fx=1.1 * size,
        fy=1.1 * size,
        cx=size / 2,
        cy=size / 2,
        width=size,
        height=size,
        near=near,
        far=far,
    )


def radiance_pattern(camera: Camera, seed: int) -> Tensor:
    """A smooth HDR image [H, W, 3] in about [0.02, 4]: a bright blob on a dim gradient."""
    gen = torch.Generator().manual_seed(seed)
    ys, xs = torch.meshgrid(torch.linspace(-1, 1, camera.height), torch.linspace(-1, 1, camera.width), indexing="ij")
    centre = torch.rand(2, generator=gen) * 0.6 - 0.3
    blob = torch.exp(-((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / 0.15)
    tint = torch.tensor([1.0, 0.7, 0.4]) + 0.2 * torch.rand(3, generator=gen)
    return (0.02 + 0.1 * (xs + 1)[..., None] + 4.0 * blob[..., None] * tint).float()


def photograph(hdr: Tensor, exposure: float) -> Tensor:
    """LDR photo of an HDR image: exposure, clip at saturation, gamma 2.2, 8-bit levels."""
    ldr = (hdr * exposure).clamp(0.0, 1.0) ** (1 / 2.2)
    return torch.round(ldr * 255.0) / 255.0


def make_scene(
    name: str = "hard",
    size: int = 16,
    train_views: int = 4,
    test_views: int = 2,
    exposure: float = 0.25,
    hdr_transform=None,
    ldr_override=None,
    camera_for=orbit_camera,
    points: Tensor | None = None,
) -> SceneData:
    """A synthetic scene. hdr_transform(hdr, index) -> hdr bends the ground truth;
    ldr_override(index) -> image replaces the photo (e.g. pure white)."""
    count = train_views + test_views
    views = []
    for index in range(count):
        camera = camera_for(index, count, size)
        hdr = radiance_pattern(camera, seed=index)
        if hdr_transform is not None:
            hdr = hdr_transform(hdr, index).float()
        image = photograph(hdr, exposure) if ldr_override is None else ldr_override(index).float()
        views.append(
            View(camera=camera, image=image, exposure=exposure, view_id=index, name=f"{name}_{index:03d}", hdr=hdr)
        )
    if points is None:
        points = torch.rand(150, 3, generator=torch.Generator().manual_seed(1)) * 1.6 - 0.8
    return SceneData(
        name=name,
        train=views[:train_views],
        test=views[train_views:],
        bounds_min=BOUNDS[0],
        bounds_max=BOUNDS[1],
        points=points,
        point_colors=torch.full_like(points, 0.5),
    )


def backbone_config(backbone: str, **overrides):
    """The smallest config of each backbone that still has its full structure."""
    if backbone == "voxel-grid":
        return VoxelGridConfig(**{"resolution": 8, "samples_per_ray": 16, **overrides})
    if backbone == "gs":
        return GaussianConfig(
            **{"sh_degree": 1, "random_init_points": 150, "strategy": DefaultStrategy(max_gaussians=500), **overrides}
        )
    if backbone == "nerf":
        field = overrides.pop("field", "cpu")
        return NerfConfig(
            field=MlpFieldConfig(
                width=16,
                depth=3,
                skip_layer=1,
                coarse_samples=8,
                fine_samples=8,
                rays_per_step=64,
                density_activation="softplus",
            )
            if field == "paper"
            else GridFieldConfig(
                levels=2,
                min_resolution=4,
                max_resolution=8,
                hidden_width=16,
                min_step=0.125,
                max_samples_per_ray=16,
                occupancy_resolution=8,
                rays_per_step=64,
                samples_per_step=512,
            ),
            render_chunk=4096,
            **overrides,
        )
    raise ValueError(f"unknown backbone {backbone!r}")


def make_trainer(
    tmp_path: Path,
    backbone: str,
    scene: SceneData,
    max_steps: int,
    method: str = "mono",
    backbone_overrides: dict | None = None,
    **overrides,
) -> Trainer:
    config = quiet_config(
        backbone_config(backbone, **(backbone_overrides or {})), tmp_path / "run", method, max_steps=max_steps
    )
    config.hdr.hidden = 32  # converters keep their structure at a quarter of the cost
    for key, value in overrides.items():
        target = config.hdr if hasattr(config.hdr, key) else config
        setattr(target, key, value)
    return Trainer(config, backbone, scene)


EXPOSURES = (0.125, 0.5, 2.0, 8.0, 32.0)


def write_disk_scene(folder: Path, size: int = 16, views: int = 6, layout: str = "hdr-nerf-synthetic") -> None:
    """The synthetic scene photographed at t1..t5, written in a dataset layout."""
    from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot, constant
    from mono_hdr_plugin.data.layouts import write_layout

    captured = []
    for index in range(views):
        camera = orbit_camera(index, views, size)
        hdr = radiance_pattern(camera, seed=index)
        shots = [Shot(t, constant(photograph(hdr, t).numpy()), f"{index}_{e}") for e, t in enumerate(EXPOSURES)]
        captured.append(
            CapturedView(index, camera, "train" if index % 2 == 0 else "test", shots, constant(hdr.numpy()))
        )
    write_layout(CapturedScene("hard-disk", captured, BOUNDS[0], BOUNDS[1]), folder, layout)


def finite_parameters(*modules: torch.nn.Module) -> list[str]:
    """Names of parameters and floating buffers that hold NaN or Inf (empty: all finite)."""
    bad = []
    for module in modules:
        for name, tensor in [*module.named_parameters(), *module.named_buffers()]:
            if tensor.is_floating_point() and not torch.isfinite(tensor).all():
                bad.append(name)
    return bad


METRIC_KEYS = ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "hdr_ssim_gt_max", "ldr_psnr", "ldr_ssim")


def train_and_check(trainer: Trainer, steps: int) -> dict:
    """Train `steps` steps, then save and evaluate through Trainer.train; assert that no step was
    skipped, every loss is finite, parameters are finite, the checkpoint loads and every metric is
    a finite number. Returns the metrics."""
    from mono_hdr_plugin.training.checkpoints import load_checkpoint

    for _ in range(steps):
        record = trainer.train_step()
        step = trainer.step
        assert not record["skipped"], f"step {step}: non-finite {record['bad_tensors']}"
        losses = {k: v for k, v in record.items() if isinstance(v, float) and k != "ldr_psnr"}
        assert all(math.isfinite(v) for v in losses.values()), f"step {step}: losses {losses}"
        assert not math.isnan(record["ldr_psnr"]), f"step {step}: LDR PSNR is NaN"
    bad = finite_parameters(trainer.backbone, trainer.method)
    assert not bad, f"non-finite parameters after {steps} steps: {bad}"
    metrics = trainer.train()  # max_steps reached: saves the checkpoint and evaluates
    assert metrics["steps"] == steps
    for key in METRIC_KEYS:
        value = metrics[key]
        if value is None and key.startswith("hdr"):
            continue  # no HDR ground truth in the test views
        # PSNR of identical images is +inf by definition (docs/robustness.md); never NaN
        ok = math.isfinite(value) or (value == math.inf and "psnr" in key)
        assert ok, f"{key} = {value}"
    payload = load_checkpoint(trainer.checkpoint_path())
    for name, tensor in _tensors(payload["pipeline"]):
        assert not tensor.is_floating_point() or torch.isfinite(tensor).all(), f"checkpoint {name}"
    return metrics


def _tensors(state: dict, prefix: str = ""):
    """(name, tensor) of a state dict, including those inside a module's extra state."""
    for name, value in state.items():
        if isinstance(value, dict):
            yield from _tensors(value, f"{prefix}{name}.")
        elif isinstance(value, torch.Tensor):
            yield prefix + name, value
