"""Tiny configurations and cameras shared by the NeRF backbone tests."""

import torch

from backbones.nerf import GridFieldConfig, MlpFieldConfig, NerfConfig
from mono_hdr_plugin.core.cameras import Camera, look_at


def tiny_field(field: str):
    """The field config of a preset ("cpu" grid or "paper" MLP), small enough for unit tests."""
    if field == "paper":
        # softplus: a 32-wide ReLU MLP can start with zero density everywhere (no gradient at all).
        return MlpFieldConfig(
            width=32, coarse_samples=8, fine_samples=8, rays_per_step=64, density_activation="softplus"
        )
    return GridFieldConfig(
        levels=2,
        min_resolution=4,
        max_resolution=8,
        hidden_width=16,
        min_step=0.25,
        max_samples_per_ray=16,
        occupancy_resolution=8,
        rays_per_step=64,
        importance_samples=0,
    )


def tiny_config(field: str, **overrides) -> NerfConfig:
    """A NerfConfig small enough for unit tests, with the same structure as the presets."""
    return NerfConfig(field=tiny_field(field), **overrides)


def orbit_camera(size: int = 8, eye=(3.0, 0.5, 1.0), near: float = 0.5, far: float = 6.0) -> Camera:
    """A small camera looking at the origin from `eye`."""
    return Camera(
        look_at(torch.tensor(eye), torch.zeros(3)),
        fx=size,
        fy=size,
        cx=size / 2,
        cy=size / 2,
        width=size,
        height=size,
        near=near,
        far=far,
    )
