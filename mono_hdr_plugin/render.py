"""Render a trained model's test views: linear HDR EXR plus LDR PNGs at chosen exposures."""

from pathlib import Path

import torch

from mono_hdr_plugin.data.dataset import SceneData
from mono_hdr_plugin.data.io import write_png
from mono_hdr_plugin.evaluation import first_per_camera, save_hdr_renders
from mono_hdr_plugin.train import load_pipeline


def srgb_encode(linear: torch.Tensor) -> torch.Tensor:
    """The sRGB transfer curve of linear values in [0, 1]."""
    linear = linear.clamp(0.0, 1.0)
    return torch.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear.clamp_min(1e-12) ** (1 / 2.4) - 0.055)


@torch.no_grad()
def render_checkpoint(checkpoint: Path, out: Path, exposures: tuple[float, ...] = (),
                      max_views: int | None = None, scene: SceneData | None = None) -> list[Path]:
    """Write <view>_hdr.exr, <view>_hdr_mulaw.png and <view>_ldr_<t>s.png for each test camera
    of the checkpoint's own data (or of `scene`, an in-memory scene)."""
    for exposure in exposures:  # checked before the (slow) checkpoint load
        if not exposure > 0:
            raise ValueError(f"--exposures must be positive seconds, got {exposure}")
    pipeline, scene, _, _ = load_pipeline(checkpoint, scene=scene)
    exposures = exposures or tuple(scene.train_exposures)
    reference_exposure = scene.train_exposures[0]
    written = []
    for view in first_per_camera(scene.test)[:max_views]:
        base = pipeline.render(view.camera, reference_exposure)
        written += save_hdr_renders(out, view, base.hdr)
        for exposure in exposures:
            if pipeline.renders_any_exposure:
                ldr = pipeline.render(view.camera, exposure).ldr
            elif exposure in scene.train_exposures:
                ldr = base.ldr
            else:  # Mono-HDR learns LDR at its training exposure only: show the HDR render instead
                ldr = srgb_encode(base.hdr * exposure / reference_exposure)
            written.append(out / f"{view.stem}_ldr_{exposure:g}s.png")
            write_png(written[-1], ldr.clamp(0, 1).numpy())
    return written
