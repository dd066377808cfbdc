"""Photometric losses of the two official recipes."""

from typing import Literal

import torch
from torch import Tensor

from mono_hdr_plugin.core.metrics import ssim

LossKind = Literal["l1_dssim", "mse"]


def l1_dssim_loss(pred: Tensor, target: Tensor, dssim_weight: float = 0.2) -> Tensor:
    """3DGS loss (1 - lambda) * L1 + lambda * (1 - SSIM) on images [H, W, C]."""
    l1 = (pred - target).abs().mean()
    return (1.0 - dssim_weight) * l1 + dssim_weight * (1.0 - ssim(pred, target))


def mse_loss(pred: Tensor, target: Tensor) -> Tensor:
    """NeRF loss: mean squared error over pixels or rays."""
    return torch.mean((pred - target) ** 2)


def photometric_loss(pred: Tensor, target: Tensor, kind: LossKind, dssim_weight: float = 0.2) -> Tensor:
    """The loss of the given kind; D-SSIM needs whole images, so pixel batches fall back to L1."""
    if kind == "mse":
        return mse_loss(pred, target)
    if pred.dim() == 3:
        return l1_dssim_loss(pred, target, dssim_weight)
    return (pred - target).abs().mean()
