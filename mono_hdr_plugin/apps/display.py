"""From linear frames to pixels on a screen: exposure, camera response, tone mapping, depth.

Outputs (the viewer's dropdown, `mono-hdr render --output`):
  ldr         the LDR photo at the chosen exposure: the learned camera response where the method
              has one (HDR-NeRF, HDR-GS); Mono-HDR's LDR branch at its training exposure, and at
              other exposures the HDR render through the sRGB display curve (it has no response
              for other exposures).
  hdr-srgb    the exposed HDR render through the sRGB curve, clipped: a camera with an ideal response.
  hdr-filmic  the exposed HDR render through the ACES filmic curve (Narkowicz's fit), then sRGB:
              highlights roll off instead of clipping.
  hdr-mulaw   mu-law of the HDR render divided by its maximum, as the HDR metrics see it (EV 0);
              each EV doubles the value before the curve.
  depth       the backbone's depth, coloured (turbo, near = warm), black where the rays are less
              than half opaque.

"Exposed HDR" is `ExposureModel.display_scale * hdr * t / reference_exposure`: linear in the
exposure time t, so one stop more doubles every value.
"""

from typing import Literal, get_args

import matplotlib
import numpy as np
import torch
from torch import Tensor

from mono_hdr_plugin.core.colour import srgb_encode
from mono_hdr_plugin.core.metrics import mu_law
from mono_hdr_plugin.training.frames import ExposureModel
from mono_hdr_plugin.training.pipeline import Frame

Output = Literal["ldr", "hdr-srgb", "hdr-filmic", "hdr-mulaw", "depth"]
OUTPUTS: tuple[str, ...] = get_args(Output)
OUTPUT_LABELS = {
    "ldr": "LDR (camera response)",
    "hdr-srgb": "HDR, sRGB curve",
    "hdr-filmic": "HDR, filmic (ACES)",
    "hdr-mulaw": "HDR, mu-law",
    "depth": "Depth",
}


def exposed_hdr(hdr: Tensor, exposure: float, model: ExposureModel) -> Tensor:
    """Linear display values of an HDR render at `exposure` seconds (1 = display white)."""
    return hdr * (model.display_scale * exposure / model.reference_exposure)


def aces_filmic(linear: Tensor) -> Tensor:
    """Krzysztof Narkowicz's fit of the ACES filmic curve: x(2.51x + 0.03) / (x(2.43x + 0.59) + 0.14),
    clipped to [0, 1]."""
    x = linear.clamp_min(0.0)
    return ((x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14)).clamp(0.0, 1.0)


def colour_map(values: Tensor, name: str) -> Tensor:
    """[H, W] values in [0, 1] (clipped) -> [H, W, 3] colours of a matplotlib colormap."""
    colours = matplotlib.colormaps[name](values.clamp(0.0, 1.0).double().numpy())[..., :3]
    return torch.from_numpy(colours).float()


def colour_depth(depth: Tensor, alpha: Tensor | None = None) -> Tensor:
    """Depth [H, W] -> [H, W, 3] in [0, 1]: turbo over the 2nd-98th percentile of the hit pixels
    (near warm, far cool), black where nothing was hit (alpha [H, W] below 0.5, or depth 0)."""
    hit = depth > 0 if alpha is None else (alpha >= 0.5) & (depth > 0)
    if not hit.any():
        return torch.zeros(*depth.shape, 3)
    values = depth[hit].double()
    near, far = torch.quantile(values, 0.02).item(), torch.quantile(values, 0.98).item()
    image = colour_map((far - depth.double()) / max(far - near, 1e-12), "turbo")
    return torch.where(hit[..., None], image, torch.zeros_like(image))


def needs_render_at(output: str, model: ExposureModel) -> bool:
    """Whether this output depends on the exposure through the renderer itself (the learned
    camera response is applied per primitive, before compositing) rather than after it."""
    return output == "ldr" and model.renders_any_exposure


def to_display(frame: Frame, output: str, exposure: float, model: ExposureModel) -> Tensor:
    """[H, W, 3] in [0, 1] of `frame` shown as `output` at `exposure` seconds.

    For an `ldr` output of a method with a learned camera response, `frame` must have been
    rendered at `exposure` (see needs_render_at); every other output reuses any frame.
    """
    if output == "ldr":
        if model.renders_any_exposure:
            if frame.exposure != exposure:
                raise ValueError(
                    f"the frame was rendered at {frame.exposure} s, not {exposure} s: "
                    "the camera response needs a render at the shown exposure"
                )
            return frame.ldr
        if model.shows_own_ldr(exposure):
            return frame.ldr
        return srgb_encode(exposed_hdr(frame.hdr, exposure, model))
    if output == "hdr-srgb":
        return srgb_encode(exposed_hdr(frame.hdr, exposure, model))
    if output == "hdr-filmic":
        return srgb_encode(aces_filmic(exposed_hdr(frame.hdr, exposure, model)))
    if output == "hdr-mulaw":
        gain = exposure / model.reference_exposure
        return mu_law((frame.hdr * gain / frame.hdr.max().clamp_min(1e-12)).clamp(0.0, 1.0))
    if output == "depth":
        if frame.depth is None:
            return torch.zeros_like(frame.hdr)
        return colour_depth(frame.depth, frame.alpha)
    raise ValueError(f"unknown output {output!r}; choose one of {', '.join(OUTPUTS)}")


def to_uint8(image: Tensor) -> np.ndarray:
    """[H, W, 3] in [0, 1] -> uint8 array, rounded."""
    return np.round(image.clamp(0.0, 1.0).numpy() * 255.0).astype(np.uint8)
