"""What the HDR-NeRF and HDR-GS baselines share: a camera response (CRF) of log radiance per primitive."""

import torch
from torch import Tensor

from mono_hdr_plugin.core.backbone import LdrFeatures
from mono_hdr_plugin.core.converters import PerChannelCRF
from mono_hdr_plugin.core.losses import LossKind
from mono_hdr_plugin.methods.base import HdrMethod, MethodConfig, MethodOutput

# Largest log radiance the baselines exponentiate: exp(30) ~ 1e13 stays finite in float32.
MAX_LOG_RADIANCE = 30.0


class CrfBaseline(HdrMethod):
    """Both baselines as their official renderers do it: colours are log radiance ln E; each primitive
    (NeRF sample, Gaussian) gets LDR = CRF(ln E + ln dt) and HDR = exp(ln E), composited in one pass."""

    renders_any_exposure = True
    hdr_recipe = (
        "raw colour r = the Gaussian's colour before the LDR activation (3DGS: SH(view direction)) is log "
        "radiance ln E; hdr = exp(min(r, 30)); the LDR colour at exposure t seconds is CRF(r + ln t) per "
        "channel i: h = relu(crf.hidden.weight[i] * x_i + crf.hidden.bias[i]); ldr_i = sigmoid(h @ "
        "crf.out.weight[i] + crf.out.bias[i]). Composite both with the same alpha weights."
    )

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__(config, loss_kind)
        self.crf = PerChannelCRF(config.hidden)

    def forward(self, features: LdrFeatures, exposure: float | Tensor) -> MethodOutput:
        log_radiance = features.raw_colors.clamp(max=MAX_LOG_RADIANCE)
        ldr_colors = self.crf(log_radiance + torch.log(torch.as_tensor(exposure, dtype=log_radiance.dtype)))
        image = features.composite(torch.cat([ldr_colors, torch.exp(log_radiance)], dim=-1))
        return MethodOutput(ldr=image[..., :3], hdr=image[..., 3:])
