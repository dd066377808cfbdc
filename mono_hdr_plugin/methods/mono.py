"""Mono-HDR: the meta-algorithm (L2H-CC per primitive, one compositing pass, H2L-CC closes the loop)."""

import torch
from torch import Tensor, nn

from mono_hdr_plugin.core.backbone import LdrFeatures
from mono_hdr_plugin.core.converters import H2LColorConverter, L2HColorConverter
from mono_hdr_plugin.core.losses import LossKind
from mono_hdr_plugin.core.metrics import normalise_hdr
from mono_hdr_plugin.methods.base import HdrMethod, MethodConfig, MethodOutput, Targets, register_method


@register_method("mono")
class MonoHDR(HdrMethod):
    """The meta-algorithm: L2H-CC per primitive, one compositing pass, H2L-CC closes the loop."""

    l2h_class: type[nn.Module] = L2HColorConverter
    h2l_class: type[nn.Module] | None = H2LColorConverter
    hdr_recipe = (
        "colour c = the Gaussian's LDR colour (3DGS: max(SH(view direction) + 0.5, 0)); hdr = L2H-CC(c) per "
        "channel i, with each hidden unit j's weights signed by its direction d_j (+1 for j < ceil(hidden / 2), "
        "else -1): w_j = d_j * |l2h.latent.weight[i, 0, j]|, a_j = d_j * |l2h.heads.weight[i, j]|; h = relu(w * c_i "
        "+ l2h.latent.bias[i]); (X, S, Y) = h @ a + l2h.heads.bias[i]; hdr_i = softplus(c_i + relu(X) * relu(S) + "
        "Y), non-decreasing in c_i. Composite hdr with the same alpha weights as the LDR colour. ldr_from_hdr = "
        "H2L-CC(mu_law(hdr_image / max)) closes the loop in training only."
    )

    def __init__(self, config: MethodConfig, loss_kind: LossKind):
        super().__init__(config, loss_kind)
        self.l2h = self.l2h_class(config.hidden)
        self.h2l = self.h2l_class(config.hidden) if self.h2l_class is not None else None

    def forward(self, features: LdrFeatures, exposure: float | Tensor) -> MethodOutput:
        hdr_colors = self.l2h(features.colors if features.l2h_inputs is None else features.l2h_inputs)
        image = features.composite(torch.cat([features.colors, hdr_colors], dim=-1))
        ldr, hdr = image[..., :3], image[..., 3:]
        # H2L-CC serves the loss only: a render (eval mode) skips it
        ldr_from_hdr = self.h2l(normalise_hdr(hdr)) if self.h2l is not None and self.training else None
        return MethodOutput(ldr=ldr, hdr=hdr, ldr_from_hdr=ldr_from_hdr)

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, Tensor]:
        terms = super().losses(output, targets, step)
        if self.config.use_h2l_loss and output.ldr_from_hdr is not None:
            terms["h2l"] = self.beta * self._loss(output.ldr_from_hdr, targets.ldr)
        return terms
