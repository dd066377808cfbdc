"""A backbone whose render is known exactly, and a scene to evaluate it on.

The backbone hands out one primitive per pixel with identity compositing, so a method's images
are its per-primitive colours. With every converter weight set to zero (`zero_method`) the
methods' renders follow in closed form:
  Mono-HDR: LDR = c, HDR = softplus(c) (L2H-CC's heads are 0);
  baselines: LDR = sigmoid(0) = 0.5 at every exposure, HDR = exp(logit(c)) = c / (1 - c).
"""

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from mono_hdr_plugin.core.backbone import Backbone, LdrFeatures, SceneInfo
from mono_hdr_plugin.core.cameras import Camera, look_at
from mono_hdr_plugin.core.registry import register_backbone
from mono_hdr_plugin.data.dataset import SceneData, View

SIZE = 16


@dataclass
class KnownRenderConfig:
    """The render is a fixed function of the camera."""

    brightness: float = 1.0
    """Scales every colour; above 1 some LDR pixels leave [0, 1] (for Mono-HDR only: the baselines
    read colours as logit(c))."""


def known_ldr(camera: Camera) -> torch.Tensor:
    """The LDR colour [*camera.output_shape, 3] of every pixel: ramps across the image, brighter for
    cameras at larger x."""
    pixels = camera.pixel_centers() - 0.5
    xs, ys = pixels[:, 0], pixels[:, 1]
    level = 0.3 + 0.05 * camera.c2w[0, 3].float()
    channels = [level + 0.3 * xs / camera.width * (c + 1) / 3 + 0.15 * ys / camera.height for c in range(3)]
    return torch.stack(channels, -1).clamp(0.02, 0.95).reshape(*camera.output_shape, 3)


@register_backbone("known-render")
class KnownRenderBackbone(Backbone):
    """Renders `known_ldr(camera)`: one primitive per pixel, composited by identity."""

    config_class = KnownRenderConfig
    loss_kind = "mse"

    def __init__(self, config: KnownRenderConfig, scene: SceneInfo):
        super().__init__(config, scene)
        self.unused = nn.Parameter(torch.zeros(1))  # Adam needs a parameter; it does not shape the render

    def render_ldr_features(self, camera: Camera) -> LdrFeatures:
        colors = self.config.brightness * known_ldr(camera).reshape(-1, 1, 3)

        def composite(values: torch.Tensor) -> torch.Tensor:
            return values.reshape(*camera.output_shape, values.shape[-1])

        return LdrFeatures(colors=colors, raw_colors=torch.logit(colors), composite=composite)


def zero_method(pipeline) -> None:
    """Every weight of the method's converters set to zero: their outputs become closed forms."""
    with torch.no_grad():
        for parameter in pipeline.method.parameters():
            parameter.zero_()


def expected_render(camera: Camera, method: str, brightness: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(LDR, HDR) the zeroed method renders for `camera`, in float64, from the closed forms above."""
    c = brightness * known_ldr(camera).double().numpy()
    if method in ("hdr-gs", "hdr-nerf"):
        return np.full_like(c, 0.5), c / (1 - c)
    return c, np.log1p(np.exp(c))


def camera_at(x: float) -> Camera:
    eye = torch.tensor([x, -3.0, 0.5])
    return Camera(
        look_at(eye, torch.tensor([x, 0.0, 0.0])),
        fx=18.0,
        fy=18.0,
        cx=SIZE / 2,
        cy=SIZE / 2,
        width=SIZE,
        height=SIZE,
        near=0.1,
        far=10.0,
    )


def ground_truth(camera: Camera, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """An LDR photo and an HDR image near the known render, different for every seed."""
    generator = torch.Generator().manual_seed(seed)
    c = known_ldr(camera)
    ldr = (c + (0.02 + 0.01 * seed) * torch.randn(c.shape, generator=generator)).clamp(0, 1)
    hdr = torch.nn.functional.softplus(c) * (3.0 + seed) * torch.exp(0.2 * torch.randn(c.shape, generator=generator))
    return ldr, hdr


def view(camera_x: float, view_id: int, exposure: float, seed: int, with_hdr: bool = True) -> View:
    camera = camera_at(camera_x)
    ldr, hdr = ground_truth(camera, seed)
    level = {0.5: 1, 2.0: 2, 8.0: 3}[exposure]
    return View(
        camera=camera,
        image=ldr,
        exposure=exposure,
        view_id=view_id,
        name=f"cam{view_id}_t{level}",
        hdr=hdr if with_hdr else None,
    )


def known_scene() -> SceneData:
    """Train exposures 0.5 and 2; test views listed out of camera order, some at exposure 8 (no
    training view has it), camera 2 without HDR ground truth, camera 1 photographed three times.

    HDR ground truth is the same image at every exposure of a camera (seed = camera id), as it is
    in real data; the LDR photos differ per view.
    """
    train = [view(-1.0, 10, 0.5, 10), view(1.5, 11, 2.0, 11)]
    test = [
        view(3.0, 3, 2.0, 3),
        view(3.0, 3, 8.0, 3),
        view(1.0, 1, 8.0, 1),
        view(1.0, 1, 0.5, 1),
        view(1.0, 1, 2.0, 1),
        view(2.0, 2, 0.5, 2, with_hdr=False),
        view(0.0, 0, 0.5, 0),
    ]
    # LDR photos differ per exposure: reseed each test photo by its position in the list
    for index, item in enumerate(test):
        item.image = ground_truth(item.camera, 100 + index)[0]
    return SceneData(
        name="known-answer", train=train, test=test, bounds_min=torch.full((3,), -4.0), bounds_max=torch.full((3,), 4.0)
    )
