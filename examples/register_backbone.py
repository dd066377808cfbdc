"""Register a new backbone in Python and train it with Mono-HDR, end to end, in seconds.

The backbone is a dense voxel grid (density + LDR colour) rendered by volume rendering:
one class, one decorator. Mono-HDR then lifts it to HDR with no other change. The capture
is made right here: an HDR voxel scene photographed at one exposure through a gamma curve.

    python examples/register_backbone.py --steps 300
"""

import argparse
from dataclasses import dataclass
from typing import ClassVar

import torch
import torch.nn.functional as F

from mono_hdr_plugin.core.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.registry import register_backbone
from mono_hdr_plugin.core.validation import POSITIVE, at_least
from mono_hdr_plugin.data.dataset import SceneData, View


@dataclass
class VoxelGridConfig:
    resolution: int = 24
    """Voxels per side of the grid spanning the scene bounds."""
    samples_per_ray: int = 48
    """Evenly spaced samples between the camera's near and far."""
    lr: float = 0.1
    """Adam learning rate of the grids."""

    flag_rules: ClassVar = {"resolution": at_least(2), "samples_per_ray": at_least(1), "lr": POSITIVE}


def sample_grid(grid: torch.Tensor, points: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Trilinear lookup of a [C, R, R, R] grid at world points [..., 3] -> [..., C] (zero outside)."""
    unit = (points - lo) / (hi - lo) * 2 - 1
    flat = unit.reshape(1, -1, 1, 1, 3)
    values = F.grid_sample(grid[None], flat, align_corners=True, padding_mode="zeros")
    return values.reshape(grid.shape[0], -1).T.reshape(*points.shape[:-1], grid.shape[0])


def volume_render(density: torch.Tensor, deltas: torch.Tensor):
    """Weights [N, S] of samples with densities [N, S] and spacings [N, S]."""
    alpha = 1 - torch.exp(-density * deltas)
    transmittance = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1] + 1e-10], 1), 1)
    return alpha * transmittance


def ray_samples(camera: Camera, count: int):
    origins, directions = camera.rays()
    origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)
    t = torch.linspace(camera.near, camera.far, count)
    points = origins[:, None] + directions[:, None] * t[None, :, None]
    deltas = torch.full((origins.shape[0], count), (camera.far - camera.near) / count)
    return points, deltas


@register_backbone("voxel-grid")
class VoxelGridBackbone(Backbone):
    config_class = VoxelGridConfig
    loss_kind = "mse"
    pixel_batch = None

    def __init__(self, config: VoxelGridConfig, scene: SceneInfo):
        super().__init__(config, scene)
        r = config.resolution
        self.register_buffer("lo", scene.bounds_min.float())
        self.register_buffer("hi", scene.bounds_max.float())
        self.density = torch.nn.Parameter(torch.full((1, r, r, r), 0.1))
        self.color_logits = torch.nn.Parameter(torch.zeros(3, r, r, r))

    def parameter_groups(self) -> list[dict]:
        return [{"name": "grid", "params": [self.density, self.color_logits], "lr": self.config.lr}]

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        points, deltas = ray_samples(camera, self.config.samples_per_ray)
        density = F.softplus(sample_grid(self.density, points, self.lo, self.hi)[..., 0] * 10)
        raw = sample_grid(self.color_logits, points, self.lo, self.hi)
        weights = volume_render(density, deltas)

        def composite(values: torch.Tensor) -> torch.Tensor:
            return (weights[..., None] * values).sum(-2).reshape(*camera.output_shape, values.shape[-1])

        return LdrFeatures(
            colors=torch.sigmoid(raw), raw_colors=raw, composite=composite, extras={"alpha": weights.sum(-1)}
        )


def make_capture(size: int = 24, views: int = 12, exposure: float = 0.5, seed: int = 0) -> SceneData:
    """An HDR voxel scene (a dim box around two bright blobs) photographed at one exposure."""
    generator = torch.Generator().manual_seed(seed)
    r = 16
    axis = torch.linspace(-1, 1, r)
    z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
    blob_a = torch.exp(-((x - 0.3) ** 2 + y**2 + z**2) / 0.08)
    blob_b = torch.exp(-((x + 0.35) ** 2 + (y - 0.2) ** 2 + (z + 0.1) ** 2) / 0.05)
    density = (4.0 * (blob_a + blob_b))[None]
    radiance = torch.stack(
        [0.05 + 6.0 * blob_a, 0.05 + 1.5 * blob_b + 0.5 * blob_a, 0.1 + 0.3 * torch.rand(r, r, r, generator=generator)]
    )
    lo, hi = torch.full((3,), -1.0), torch.full((3,), 1.0)
    scene_views = []
    for index in range(views):
        angle = 2 * torch.pi * index / views
        eye = torch.tensor([2.6 * torch.cos(torch.tensor(angle)), 2.6 * torch.sin(torch.tensor(angle)), 0.8])
        camera = Camera(
            look_at(eye, torch.zeros(3)),
            fx=size * 1.1,
            fy=size * 1.1,
            cx=size / 2,
            cy=size / 2,
            width=size,
            height=size,
            near=1.2,
            far=4.0,
        )
        points, deltas = ray_samples(camera, 64)
        weights = volume_render(F.relu(sample_grid(density, points, lo, hi)[..., 0]), deltas)
        hdr = (weights[..., None] * sample_grid(radiance, points, lo, hi)).sum(-2).reshape(size, size, 3)
        ldr = (hdr * exposure).clamp(0, 1) ** (1 / 2.2)
        scene_views.append(
            View(camera=camera, image=ldr, exposure=exposure, view_id=index, name=f"view_{index:03d}", hdr=hdr)
        )
    return SceneData(name="voxel-blobs", train=scene_views[0::2], test=scene_views[1::2], bounds_min=lo, bounds_max=hi)


def main() -> None:
    from mono_hdr_plugin.training.config import train_config_for
    from mono_hdr_plugin.training.trainer import Trainer

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--method", default="mono")
    args = parser.parse_args()
    scene = make_capture()
    config = train_config_for(VoxelGridConfig, args.method)(
        max_steps=args.steps, quiet=True, save_renders=False, checkpoint_every=10**9
    )
    config.out = config.out.parent / "voxel-grid-example"
    trainer = Trainer(config, "voxel-grid", scene)
    before = trainer.evaluate()
    after = trainer.train()
    print(
        f"voxel-grid + {args.method}: HDR PSNR {before['hdr_psnr']:.2f} dB at step 0 -> "
        f"{after['hdr_psnr']:.2f} dB after {args.steps} steps ({after['train_seconds']:.1f} s)"
    )


if __name__ == "__main__":
    main()
