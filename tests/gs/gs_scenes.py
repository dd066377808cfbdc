"""Scenes shared by the Gaussian tests: random, hard-case (docs/robustness.md), cameras."""

import torch

from mono_hdr_plugin.core.cameras import Camera, look_at


def make_camera(width: int = 40, height: int = 32, near: float = 0.05) -> Camera:
    c2w = look_at(torch.tensor([0.3, -4.0, 0.5]), torch.zeros(3))
    focal = 0.9 * width
    return Camera(
        c2w,
        fx=focal,
        fy=focal * 1.05,
        cx=0.5 * width + 0.7,
        cy=0.5 * height - 0.4,
        width=width,
        height=height,
        near=near,
    )


def random_gaussians(n: int, seed: int = 0, channels: int = 3, dtype=torch.float32) -> dict:
    """Gaussians scattered around the origin, sizes from sub-pixel to a few tiles."""
    gen = torch.Generator().manual_seed(seed)
    return {
        "means": (torch.rand(n, 3, generator=gen) * 2 - 1).to(dtype) * 1.2,
        "quats": torch.randn(n, 4, generator=gen).to(dtype),
        "scales": torch.exp(torch.rand(n, 3, generator=gen) * 3 - 5.5).to(dtype),
        "opacities": (torch.rand(n, generator=gen) * 0.98 + 0.01).to(dtype),
        "values": torch.rand(n, channels, generator=gen).to(dtype),
    }


def hard_gaussians(camera: Camera, channels: int = 3) -> dict:
    """docs/robustness.md: every numerically awkward Gaussian we know, plus ordinary ones."""
    base = random_gaussians(40, seed=7, channels=channels)
    forward = camera.c2w[:3, 2]
    eye = camera.center
    rows = []  # (mean, quat, scale, opacity)
    rows.append((eye + 2.0 * forward, [0.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.1], 0.7))  # zero quaternion
    rows.append((eye + 3.0 * forward, [1.0, 0.2, 0.0, 0.0], [0.0, 0.0, 0.0], 0.8))  # zero covariance
    rows.append((eye + 3.0 * forward, [0.3, 0.1, 0.9, 0.0], [0.3, 0.0, 0.0], 0.8))  # needle, rank 1
    rows.append((eye + 3.0 * forward, [1.0, 0.0, 0.0, 0.0], [1e20, 1e20, 1e20], 0.5))  # overflowing
    rows.append((eye - 1.0 * forward, [1.0, 0.0, 0.0, 0.0], [0.2, 0.2, 0.2], 0.9))  # behind camera
    rows.append((eye + 0.0 * forward, [1.0, 0.0, 0.0, 0.0], [0.2, 0.2, 0.2], 0.9))  # at the eye
    rows.append((eye + 0.051 * forward, [1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5], 0.6))  # straddles near
    rows.append((eye + 0.3 * forward, [0.5, 0.5, 0.5, 0.5], [30.0, 30.0, 0.01], 0.5))  # huge radius
    rows.append((eye + 2.5 * forward, [1.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1], 1.0 - 1e-7))  # opacity ~ 1
    rows.append((eye + 2.6 * forward, [1.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1], 1.0))  # opacity 1
    rows.append((eye + 2.7 * forward, [1.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1], 1e-6))  # opacity ~ 0
    rows.append((eye + 2.7 * forward, [1.0, 0.0, 0.0, 0.0], [0.2, 0.1, 0.1], 0.0))  # opacity 0
    rows.append(
        (eye + 2.0 * forward + 40.0 * camera.c2w[:3, 0], [1.0, 0.0, 0.0, 0.0], [0.5, 0.5, 0.5], 0.9)
    )  # far off-screen
    extra = {
        "means": torch.stack([torch.as_tensor(r[0], dtype=torch.float32) for r in rows]),
        "quats": torch.tensor([r[1] for r in rows]),
        "scales": torch.tensor([r[2] for r in rows]),
        "opacities": torch.tensor([r[3] for r in rows]),
        "values": torch.rand(len(rows), channels, generator=torch.Generator().manual_seed(3)),
    }
    return {k: torch.cat([base[k], extra[k]]) for k in base}


def pixel_weights(height: int, width: int, channels: int, seed: int = 11) -> torch.Tensor:
    """Random per-pixel loss weights, so every pixel's gradient is tested."""
    return torch.rand(height, width, channels, generator=torch.Generator().manual_seed(seed)) - 0.3
