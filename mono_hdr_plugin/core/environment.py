"""What lies at infinity (sky, sun, a distant horizon) as a learned function of direction.

A backbone that renders unbounded scenes composites it behind its own primitives with weight
(1 - alpha): 3DGS behind the splats, NeRF after the last sample. The map holds raw values (the
backbone's colours before its LDR activation), so the meta-algorithm's converters lift it to HDR
like any other primitive's colour.

The map is a latitude-longitude texture pyramid: the sum of bilinear lookups into textures of
widths `width`, `width / 4`, ... (each half as tall as wide). The coarse levels learn smooth sky
from few steps (one texel collects the gradient of many pixels); the finest level holds a sun a
few pixels wide.
"""

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def sky_frame(up: Tensor) -> Tensor:
    """[3, 3] rotation whose rows are the map's x, y and z axes in world coordinates; z is `up`."""
    z = up.double() / up.double().norm()
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(z @ helper)) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    x = helper - (helper @ z) * z
    x = x / x.norm()
    return torch.stack([x, torch.linalg.cross(z, x), z]).float()


def direction_to_uv(directions: Tensor, frame: Tensor) -> Tensor:
    """Directions [..., 3] (any length) -> [..., 2] in [-1, 1]: u the azimuth (-pi..pi), v the
    elevation from straight up (-1) to straight down (+1), as grid_sample reads them."""
    local = F.normalize(directions, dim=-1) @ frame.T
    azimuth = torch.atan2(local[..., 1], local[..., 0])
    elevation = torch.asin(local[..., 2].clamp(-1.0, 1.0))
    return torch.stack([azimuth / math.pi, -elevation / (math.pi / 2)], dim=-1)


def sample_latlong(texture: Tensor, uv: Tensor) -> Tensor:
    """Bilinear lookup of texture [C, H, W] at uv [N, 2] -> [N, C], wrapping around in azimuth.

    One column of the other side is padded onto each side, so a lookup at the seam (u = +-1) blends
    the first and last columns as it would anywhere else on the sphere.
    """
    channels, _, width = texture.shape
    padded = torch.cat([texture[..., -1:], texture, texture[..., :1]], dim=-1)
    u = uv[:, 0] * width / (width + 2)  # the padded texture is 2 texels wider
    grid = torch.stack([u, uv[:, 1]], dim=-1)[None, None]
    sampled = F.grid_sample(padded[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return sampled[0, :, 0].T.reshape(-1, channels)


class EnvironmentMap(nn.Module):
    """Raw values at infinity: `forward(directions [..., 3]) -> [..., channels]`.

    up: the world's up direction (the map's pole), width: texels around the finest level's
    equator, levels: textures in the pyramid, initial: the raw value everywhere at the start.
    """

    def __init__(self, up: Tensor, width: int = 512, levels: int = 4, channels: int = 3, initial: float = 0.0):
        super().__init__()
        if width < 4 or width % 2 or levels < 1 or width >> (2 * (levels - 1)) < 4:
            raise ValueError(
                f"environment map: width {width} must be even and leave >= 4 texels at each of {levels} levels"
            )
        self.frame: Tensor
        self.register_buffer("frame", sky_frame(up))
        widths = [width >> (2 * level) for level in range(levels)]
        # All of the initial value in the coarsest level: the finer ones start as pure detail (zero).
        self.textures = nn.ParameterList(
            nn.Parameter(torch.full((channels, w // 2, w), initial if w == widths[-1] else 0.0)) for w in widths
        )

    def forward(self, directions: Tensor) -> Tensor:
        shape = directions.shape[:-1]
        uv = direction_to_uv(directions.reshape(-1, 3), self.frame)
        values = sum(sample_latlong(texture, uv) for texture in self.textures)
        return torch.as_tensor(values).reshape(*shape, -1)


def up_from_cameras(c2ws: Tensor) -> Tensor:
    """The mean up direction of OpenCV cameras [N, 4, 4] (their -y axis): the sky's pole for a capture
    whose photos are held upright, whatever the world's axes."""
    up = -c2ws[:, :3, 1].double().mean(0)
    if float(up.norm()) < 1e-6:
        raise ValueError("the cameras' up directions cancel out: pass the world's up direction explicitly")
    return (up / up.norm()).float()
