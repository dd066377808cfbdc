"""Image metrics: PSNR, SSIM (scikit-image / 3DGS settings), mu-law HDR metrics, optional LPIPS.

HDR scores (docs/method.md, "Which HDR score to read"): own-max and GT-max are the official
protocols; aligned and emitter-masked are ours, so that one peak pixel cannot swing a score.

All functions take torch tensors [H, W, C] (or [N, C] for PSNR) with LDR values in [0, 1].
"""

import functools
import math
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from mono_hdr_plugin.core.calibration import median_log_ratio, well_exposed, well_exposed_channels

MU = 5000.0
EMITTER_FRACTION = 0.001
"""The emitter-masked HDR PSNR leaves out this fraction of pixels: the ground truth's brightest."""
SOURCE_LEVEL = 0.5
"""A light source (the sun, a bulb) is where the ground truth's brightest channel reaches this fraction of
its maximum."""
CHROMA_BOUND = 0.05
"""A pixel's colour is wrong (a coloured floater) when its chromaticity is off by more than this."""
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # scikit-image: int(truncate * sigma + 0.5) with truncate = 3.5
SSIM_WINDOW = 2 * SSIM_RADIUS + 1
"""The fewest pixels a side SSIM (and so training, evaluation and the D-SSIM loss) can score."""


def psnr(pred: Tensor, target: Tensor, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB; identical images give +inf (reported as such)."""
    if pred.shape != target.shape:
        raise ValueError(f"psnr: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    mse = torch.mean((pred.double() - target.double()) ** 2).item()
    return math.inf if mse == 0.0 else 10.0 * math.log10(data_range**2 / mse)


def _gaussian_window(dtype: torch.dtype) -> Tensor:
    offsets = torch.arange(-SSIM_RADIUS, SSIM_RADIUS + 1, dtype=dtype)
    kernel = torch.exp(-(offsets**2) / (2 * SSIM_SIGMA**2))
    return kernel / kernel.sum()


def ssim_map(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Per-pixel SSIM [H - 10, W - 10, C] of two images [H, W, C].

    Gaussian window (sigma 1.5, 11 taps), population covariance, K1 = 0.01, K2 = 0.03: the
    3DGS SSIM. Only windows that lie inside the image are kept, which is exactly the region
    scikit-image averages (it crops the border its padding touched), so the mean matches
    `skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=1, channel_axis=-1)`. Differentiable in `pred`; on the
    CPU, with a constant `target` (a loss's), it runs the fused C++ kernel, else `ssim_map_reference`.
    """
    _check_ssim_shapes(pred, target)
    if pred.device.type != "cpu" or target.requires_grad:
        return ssim_map_reference(pred, target, data_range)
    x, y = pred.permute(2, 0, 1).contiguous(), target.permute(2, 0, 1).contiguous()
    return _FusedSsim.apply(x, y.to(x.dtype), _gaussian_window(x.dtype), *_ssim_constants(data_range)).permute(1, 2, 0)


def _ssim_constants(data_range: float) -> tuple[float, float]:
    """C1 = (K1 L)^2 and C2 = (K2 L)^2 with K1 = 0.01, K2 = 0.03 and L the data range."""
    return (0.01 * data_range) ** 2, (0.03 * data_range) ** 2


def _check_ssim_shapes(pred: Tensor, target: Tensor) -> None:
    if pred.shape != target.shape:
        raise ValueError(f"ssim: shapes differ, {tuple(pred.shape)} vs {tuple(target.shape)}")
    height, width, _ = pred.shape
    if min(height, width) < SSIM_WINDOW:
        raise ValueError(f"ssim needs images of at least {SSIM_WINDOW} pixels per side, got {height}x{width}")


def ssim_map_reference(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """`ssim_map` in torch layers (the fused kernel's twin; differentiable in both images)."""
    _check_ssim_shapes(pred, target)
    channels = pred.shape[-1]
    window = _gaussian_window(pred.dtype)
    # [1, 5C, H, W]: x, y, x^2, y^2, xy filtered together by one separable depthwise convolution
    # (as groups: on the CPU that is ~10x faster than the same filter over a batch of 5C images).
    x, y = pred.permute(2, 0, 1), target.permute(2, 0, 1)
    stack = torch.cat([x, y, x * x, y * y, x * y]).unsqueeze(0)
    maps = stack.shape[1]
    filtered = F.conv2d(stack, window.view(1, 1, -1, 1).repeat(maps, 1, 1, 1), groups=maps)
    filtered = F.conv2d(filtered, window.view(1, 1, 1, -1).repeat(maps, 1, 1, 1), groups=maps).squeeze(0)
    mu_x, mu_y, xx, yy, xy = filtered.split(channels)
    var_x, var_y, cov = xx - mu_x**2, yy - mu_y**2, xy - mu_x * mu_y
    c1, c2 = _ssim_constants(data_range)
    numerator = (2 * mu_x * mu_y + c1) * (2 * cov + c2)
    denominator = (mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2)
    return (numerator / denominator).permute(1, 2, 0)


class _FusedSsim(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, y, window, c1, c2):
        map, statistics = _ssim_extension().ssim_forward(x, y, window, c1, c2)
        ctx.save_for_backward(x, y, statistics, window)
        ctx.constants = (c1, c2)
        return map

    @staticmethod
    def backward(ctx, grad_map):
        x, y, statistics, window = ctx.saved_tensors
        grad_x = _ssim_extension().ssim_backward(grad_map.contiguous(), x, y, statistics, window, *ctx.constants)
        return grad_x, None, None, None, None


def _ssim_extension():
    from mono_hdr_plugin.core.cpp_extensions import load_cpp_extension

    return load_cpp_extension("ssim", Path(__file__).parent / "csrc" / "ssim.cpp")


def ssim(pred: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Mean SSIM of two images [H, W, C] (scalar tensor, differentiable)."""
    return ssim_map(pred, target, data_range).mean()


def mu_law(x: Tensor) -> Tensor:
    """mu-law tone map T(x) = log(1 + 5000 x) / log(5001) of values in [0, 1]."""
    return torch.log1p(MU * x) / math.log1p(MU)


def normalise_hdr(hdr: Tensor, reference_max: Tensor | None = None) -> Tensor:
    """HDR -> [0, 1]: divide by a maximum (the image's own unless given), clamp, mu-law.

    An all-zero image stays zero instead of dividing by zero. Half-precision input is computed
    in float32: float16 rounds the 1e-12 floor to 0, and 0 / 0 is NaN.
    """
    work = hdr.float() if hdr.dtype in (torch.float16, torch.bfloat16) else hdr
    peak = work.max() if reference_max is None else reference_max.to(work.dtype)
    return mu_law((work / peak.clamp_min(1e-12)).clamp(0.0, 1.0)).to(hdr.dtype)


HdrNormalisation = Literal["own_max", "gt_max"]


def tone_mapped_pair(pred_hdr: Tensor, gt_hdr: Tensor, normalisation: HdrNormalisation) -> tuple[Tensor, Tensor]:
    """The official evaluations' mu-law images of a predicted and a ground-truth HDR image.

    own_max (Mono-HDR-GS): prediction by its own max, GT by its own max then quantised to
    8 bits as the official code's PIL image is. gt_max (Mono-HDR-NeRF eval_hdr.py): both by
    the GT max, so the prediction's absolute scale counts.
    """
    gt_max = gt_hdr.max()
    if normalisation == "own_max":
        gt = torch.round(normalise_hdr(gt_hdr) * 255.0) / 255.0
        return normalise_hdr(pred_hdr), gt
    return normalise_hdr(pred_hdr, gt_max), normalise_hdr(gt_hdr, gt_max)


def hdr_metrics(pred_hdr: Tensor, gt_hdr: Tensor) -> dict[str, float]:
    """mu-law PSNR/SSIM under both official normalisations, named."""
    results = {}
    normalisations: tuple[tuple[HdrNormalisation, str], ...] = (("own_max", ""), ("gt_max", "_gt_max"))
    for normalisation, suffix in normalisations:
        pred, gt = tone_mapped_pair(pred_hdr, gt_hdr, normalisation)
        results[f"hdr_psnr{suffix}"] = psnr(pred, gt)
        results[f"hdr_ssim{suffix}"] = ssim(pred.double(), gt.double()).item()
    return results


def emitter_mask(gt_hdr: Tensor) -> Tensor:
    """[H, W] False at the ground truth's brightest ceil(EMITTER_FRACTION x pixels) pixels (by their
    brightest channel: the lights and the sun), True elsewhere."""
    peaks = gt_hdr.reshape(-1, gt_hdr.shape[-1]).amax(-1)
    left_out = math.ceil(EMITTER_FRACTION * peaks.numel())
    keep = torch.ones_like(peaks, dtype=torch.bool)
    keep[torch.topk(peaks, left_out).indices] = False
    return keep.reshape(gt_hdr.shape[:-1])


def aligning_scale(pred_hdr: Tensor, gt_hdr: Tensor) -> float:
    """The global scale that brings the prediction to the ground truth: the median of gt / pred over
    the positive values of the pixels `emitter_mask` keeps (1.0 when there are none)."""
    keep = emitter_mask(gt_hdr)
    return median_log_ratio(gt_hdr[keep], pred_hdr[keep])[0]


def hdr_scale_metrics(pred_hdr: Tensor, gt_hdr: Tensor, photo: Tensor) -> dict[str, float]:
    """The scores of the HDR's absolute level and of all but its brightest pixels:

    hdr_psnr_aligned: GT-max mu-law PSNR of the prediction times `aligning_scale` (the best global
        scale for this view: what GT-max would be if the calibration were exact);
    hdr_psnr_masked: GT-max mu-law PSNR over the pixels `emitter_mask` keeps;
    hdr_median_ratio: median of pred / gt over the positive values of pixels the photo exposes well
        (every channel inside core.calibration.WELL_EXPOSED), NaN when there are none: 1 when the
        calibrated level is right.
    """
    gt_max = gt_hdr.max()
    pred, gt = normalise_hdr(pred_hdr * aligning_scale(pred_hdr, gt_hdr), gt_max), normalise_hdr(gt_hdr, gt_max)
    keep = emitter_mask(gt_hdr)
    exposed = well_exposed(photo)
    ratio, count = median_log_ratio(pred_hdr[exposed], gt_hdr[exposed])
    return {
        "hdr_psnr_aligned": psnr(pred, gt),
        "hdr_psnr_masked": psnr(normalise_hdr(pred_hdr, gt_max)[keep], gt[keep]),
        "hdr_median_ratio": ratio if count else math.nan,
    }


def source_region(gt_hdr: Tensor) -> Tensor:
    """[H, W] True where the ground truth's brightest channel reaches SOURCE_LEVEL x its maximum,
    grown by one pixel, so a source rendered one pixel off still counts as found."""
    peaks = gt_hdr.amax(-1)
    region = (peaks >= SOURCE_LEVEL * peaks.max()).float()[None, None]
    return F.max_pool2d(region, kernel_size=3, stride=1, padding=1)[0, 0] > 0


def source_metrics(pred_hdr: Tensor, gt_hdr: Tensor, pred_ldr: Tensor, photo: Tensor) -> dict[str, float]:
    """Whether the brightest source of the view survives, read on `source_region`:

    hdr_peak_ratio: the prediction's brightest channel there, at its maximum, over the ground truth's
        maximum (1: the peak is right; 2 or 0.5 is a factor of 2 off; near 0: the source is lost);
    ldr_peak_ratio: the same for the LDR render against the photo (a clipped sun drawn clipped: 1).
    """
    region = source_region(gt_hdr)
    hdr = float(pred_hdr.amax(-1)[region].max() / gt_hdr.amax(-1).max().clamp_min(1e-12))
    ldr = float(pred_ldr.amax(-1)[region].max() / photo.amax(-1)[region].max().clamp_min(1e-12))
    return {"hdr_peak_ratio": hdr, "ldr_peak_ratio": ldr}


def chroma_outliers(pred_hdr: Tensor, gt_hdr: Tensor, photo: Tensor) -> float:
    """Fraction of the pixels the test photo exposes well whose chromaticity (r, g, b) / (r + g + b) is
    off by more than CHROMA_BOUND in any channel: coloured floaters, sky painted onto the foreground.
    Chromaticity ignores the level, so the score needs no calibration. Only well-exposed pixels count
    (core.calibration.WELL_EXPOSED): in a pixel the photo clips or buries in noise and quantisation,
    the LDR training data holds no colour to get right. NaN when no pixel is well exposed."""
    counted = well_exposed(photo) & (gt_hdr.sum(-1) > 0)
    if not counted.any():
        return math.nan
    gt_chroma = gt_hdr[counted] / gt_hdr[counted].sum(-1, keepdim=True)
    pred_chroma = pred_hdr[counted] / pred_hdr[counted].sum(-1, keepdim=True).clamp_min(1e-12)
    return float(((pred_chroma - gt_chroma).abs().amax(-1) > CHROMA_BOUND).double().mean())


CHANNELS = ("r", "g", "b")
MIN_CONSISTENCY_SAMPLES = 64
"""Fewer well-exposed values of a channel than this: its consistency scores are NaN."""
RANK_CORRELATION_FLOOR = 0.98
LOG_SLOPE_RANGE = (0.9, 1.1)
"""Radiance-consistency bounds below / outside which a run warns that its HDR is not radiance."""


OWN_LDR_PREFIX = "hdr_own_ldr_"
"""Keys of the scores against the model's own LDR render (`radiance_consistency`'s `prefix`)."""


def radiance_consistency(
    pred_hdr: Tensor, linear_photo: Tensor, photo: Tensor, prefix: str = "hdr_"
) -> dict[str, float]:
    """Scores of an HDR render [..., 3] that need no HDR ground truth, per channel, over the values the
    photo [..., 3] exposes well (core.calibration.WELL_EXPOSED, channel by channel):

    <prefix>rank_correlation_<c>: Spearman's rank correlation (ties ranked by their mean) of the HDR
        with the linearised photo `linear_photo` (f^-1(photo)): 1 when the HDR rises wherever the photo does;
    <prefix>log_slope_<c>: the least-squares slope of log HDR against log linearised photo: 1 when the
        HDR is proportional to the radiance the photo records, 0.5 when it is its square root.
    NaN where a channel has fewer than MIN_CONSISTENCY_SAMPLES usable values. `photo` may be the model's
    own LDR render (prefix OWN_LDR_PREFIX): the test photo's scores also count every way the model
    misses the photo (a blurred edge lowers the rank correlation, and, as error in the regressor, pulls
    the least-squares slope toward 0), its own LDR's only the HDR branch's departure from the response."""
    from scipy.stats import spearmanr

    usable = well_exposed_channels(photo) & (pred_hdr > 0) & (linear_photo > 0)
    scores: dict[str, float] = {}
    for channel, name in enumerate(CHANNELS):
        rank_key, slope_key = f"{prefix}rank_correlation_{name}", f"{prefix}log_slope_{name}"
        keep = usable[..., channel]
        hdr = pred_hdr[..., channel][keep].double()
        linear = linear_photo[..., channel][keep].double()
        if hdr.numel() < MIN_CONSISTENCY_SAMPLES or float(linear.std()) == 0.0:
            scores[rank_key] = scores[slope_key] = math.nan
            continue
        # a constant HDR does not follow the photo at all: 0 (spearmanr would warn and return NaN)
        rank = spearmanr(hdr.numpy(), linear.numpy()).statistic if float(hdr.std()) > 0.0 else 0.0
        scores[rank_key] = float(rank)
        x, y = torch.log(linear), torch.log(hdr)
        x, y = x - x.mean(), y - y.mean()
        scores[slope_key] = float((x * y).sum() / (x * x).sum())
    return scores


def radiance_warnings(scores: dict[str, float | None]) -> list[str]:
    """What `radiance_consistency`'s (averaged) scores say is wrong, one line per channel off: against
    the test photos, and against the model's own LDR renders where those were scored. A channel that
    misses the photos but follows its own LDR is said to be the model's miss of the photos."""
    warnings = []
    for name in CHANNELS:
        own = _consistency_faults(scores, OWN_LDR_PREFIX, name)
        photo = _consistency_faults(scores, "hdr_", name)
        own_scored = scores.get(f"{OWN_LDR_PREFIX}rank_correlation_{name}") is not None
        for fault in photo:
            line = f"the HDR's {name} channel {fault} the test photos"
            if own_scored and not own:
                line += (
                    ", while it follows the model's own LDR renders (rank correlation "
                    f"{scores[f'{OWN_LDR_PREFIX}rank_correlation_{name}']:.3f}, power "
                    f"{scores[f'{OWN_LDR_PREFIX}log_slope_{name}']:.3f}): the model misses the photos "
                    "(see ldr_psnr), its HDR is the radiance of what it renders"
                )
            warnings.append(line)
        warnings += [f"the HDR's {name} channel {fault} the model's own LDR renders" for fault in own]
    return warnings


def _consistency_faults(scores: dict[str, float | None], prefix: str, name: str) -> list[str]:
    """How one channel's scores under `prefix` fall outside RANK_CORRELATION_FLOOR / LOG_SLOPE_RANGE."""
    low, high = LOG_SLOPE_RANGE
    rank, slope = scores.get(f"{prefix}rank_correlation_{name}"), scores.get(f"{prefix}log_slope_{name}")
    faults = []
    if rank is not None and math.isfinite(rank) and rank < RANK_CORRELATION_FLOOR:
        faults.append(f"has rank correlation {rank:.3f} (below {RANK_CORRELATION_FLOOR}) with")
    if slope is not None and math.isfinite(slope) and not low <= slope <= high:
        faults.append(f"grows as the power {slope:.3f} (radiance: 1, accepted {low}-{high}) of")
    return faults


def clipped_split_metrics(pred_hdr: Tensor, gt_hdr: Tensor, photo: Tensor) -> dict[str, float]:
    """GT-max mu-law PSNR apart on the pixels the photo clips (any channel at 1: there the HDR is
    extrapolated) and on the rest; the clipped pixels' share. NaN for an empty part."""
    clipped = (photo >= 1.0).any(-1)
    gt_max = gt_hdr.max()
    pred, gt = normalise_hdr(pred_hdr, gt_max), normalise_hdr(gt_hdr, gt_max)
    return {
        "hdr_psnr_clipped": psnr(pred[clipped], gt[clipped]) if clipped.any() else math.nan,
        "hdr_psnr_unclipped": psnr(pred[~clipped], gt[~clipped]) if (~clipped).any() else math.nan,
        "clipped_fraction": float(clipped.double().mean()),
    }


class LpipsUnavailable(RuntimeError):
    """LPIPS needs network weights that are not on this machine."""


@functools.cache
def load_lpips():
    """The LPIPS (AlexNet) metric if its package and weights are installed locally.

    Raises LpipsUnavailable with the reason otherwise; nothing is downloaded.
    """
    try:
        import lpips  # optional dependency
    except ImportError as error:
        raise LpipsUnavailable(
            "LPIPS skipped: the 'lpips' package is not installed (pip install lpips, with its AlexNet weights cached)"
        ) from error
    try:
        return lpips.LPIPS(net="alex", verbose=False, pretrained=True)
    except Exception as error:  # a download attempt fails without network
        raise LpipsUnavailable(f"LPIPS skipped: its network weights are not available locally ({error})") from error


def lpips_distance(model, pred: Tensor, target: Tensor) -> float:
    """LPIPS between two images [H, W, 3] in [0, 1] (the network takes [-1, 1])."""

    def to_network(image: Tensor) -> Tensor:
        return image.permute(2, 0, 1).unsqueeze(0).float() * 2 - 1

    with torch.no_grad():
        return model(to_network(pred), to_network(target)).item()
