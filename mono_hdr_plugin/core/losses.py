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


LOG_FLOOR = 1e-4
"""log_ratio adds this fraction of the target's mean to both images before the log: a
dead channel (0) costs a large but finite error with a bounded gradient."""


def log_ratio(pred: Tensor, target: Tensor) -> Tensor:
    """log pred - log target, each with LOG_FLOOR x the target's mean added: finite on dead channels."""
    floor = LOG_FLOOR * target.mean().detach()
    return torch.log(pred + floor) - torch.log(target + floor)


def log_ratio_loss(pred: Tensor, target: Tensor) -> Tensor:
    """mean |log pred - log target| over the entries of two radiances: a relative error that also fixes
    the level (the HDR prior, methods.base: the target is the photo's own radiance)."""
    return log_ratio(pred, target).abs().mean()


def scale_invariant_log_loss(pred: Tensor, target: Tensor) -> Tensor:
    """min over c of mean |d - c| over the entries of two HDR radiances [N, 3], d = log pred - log target.

    A relative error, blind to the overall level (as L_hdr is, which divides each image by its own
    maximum): a pixel at 1e-6 of the sun's radiance whose red channel is dead costs as much as a sun
    pixel off by the same factor, where mu-law over the maximum barely sees it. The minimising c is
    d's median (the midpoint of the two middle values); it is held constant in the gradient, which is
    then the gradient of the minimum."""
    difference = log_ratio(pred, target)
    flat = difference.detach().flatten()
    middle = 0.5 * (flat.kthvalue((flat.numel() + 1) // 2).values + flat.kthvalue(flat.numel() // 2 + 1).values)
    return (difference - middle).abs().mean()
