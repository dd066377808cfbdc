"""HDR-NeRF: the CRF baseline with its unit-exposure loss and its CRF learning-rate warm-up."""

from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor

from mono_hdr_plugin.core.validation import NON_NEGATIVE, between
from mono_hdr_plugin.methods.base import MethodOutput, Targets, register_method
from mono_hdr_plugin.methods.crf_baseline import CrfBaseline


@dataclass
class HdrNerfOptions:
    """HDR-NeRF's own flags (`--method hdr-nerf`)."""

    unit_exposure_weight: float = 0.5
    """HDR-NeRF: weight of the loss pinning CRF(ln 1) to unit_exposure_value."""
    unit_exposure_value: float = 0.5
    """HDR-NeRF: CRF output at unit exposure (0.5 synthetic, 0.73 real scenes)."""
    crf_warmup_steps: int = 500
    """HDR-NeRF: the CRF learning rate ramps up linearly over these first steps (HDR-GS has no warm-up)."""

    flag_rules: ClassVar = {
        "unit_exposure_weight": NON_NEGATIVE,
        "unit_exposure_value": between(0, 1, low_open=True, high_open=True),
        "crf_warmup_steps": NON_NEGATIVE,
    }


@register_method("hdr-nerf")
class HdrNerfBaseline(CrfBaseline):
    """HDR-NeRF: the shared baseline plus its unit-exposure loss pinning the CRF at ln dt = 0 and
    its CRF learning-rate warm-up."""

    options_class = HdrNerfOptions

    def losses(self, output: MethodOutput, targets: Targets, step: int) -> dict[str, Tensor]:
        terms = super().losses(output, targets, step)
        unit = self.crf(torch.zeros(1, 3, device=output.ldr.device))
        terms["unit_exposure"] = self.options.unit_exposure_weight * torch.mean(
            (unit - self.options.unit_exposure_value) ** 2
        )
        return terms

    def learning_rate(self, group_name: str, step: int, base_lr: float) -> float:
        warmup = self.options.crf_warmup_steps
        return base_lr if warmup <= 0 else base_lr * min(1.0, (step + 1) / warmup)
