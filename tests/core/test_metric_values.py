"""Every figure the README reports, pinned against references that do not use our code.

mu-law values worked out by hand, PSNR and SSIM from scikit-image on arrays built with numpy,
and an HDR pair whose PSNR under both normalisations is derived step by step in the test. A
changed constant (mu, the SSIM window, the 8-bit quantisation of the ground truth), a swapped
argument or a metric computed against the wrong image moves these numbers.
"""

import math
import sys

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from mono_hdr_plugin.core.metrics import (
    LpipsUnavailable,
    hdr_metrics,
    load_lpips,
    lpips_distance,
    mu_law,
    normalise_hdr,
    psnr,
    ssim,
    ssim_map,
    tone_mapped_pair,
)

LN_5001 = math.log(5001.0)


def mu_law_numpy(x: np.ndarray) -> np.ndarray:
    """T(x) = ln(1 + 5000 x) / ln(5001): the mu-law of both official evaluations, written out again."""
    return np.log1p(5000.0 * x) / LN_5001


def skimage_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """The 3DGS SSIM settings in scikit-image."""
    return structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1
    )


def two_region_pair(dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """16 x 16 HDR images, left half bright, right half dim: ground truth 8 | 1, prediction 4 | 1."""
    gt = torch.ones(16, 16, 3, dtype=dtype)
    gt[:, :8] = 8.0
    pred = torch.ones(16, 16, 3, dtype=dtype)
    pred[:, :8] = 4.0
    return pred, gt


class TestMuLawByHand:
    def test_values(self):
        # 1/5000 maps to ln 2 / ln 5001, 3/5000 to ln 4 / ln 5001, 1/2 to ln 2501 / ln 5001
        x = torch.tensor([0.0, 1 / 5000, 3 / 5000, 0.5, 1.0], dtype=torch.float64)
        expected = torch.tensor(
            [0.0, math.log(2) / LN_5001, 2 * math.log(2) / LN_5001, math.log(2501) / LN_5001, 1.0], dtype=torch.float64
        )
        torch.testing.assert_close(mu_law(x), expected, rtol=1e-12, atol=0)

    def test_decimal_values(self):
        """The same values as decimals, so a changed mu (5000 -> 5001) moves them."""
        got = mu_law(torch.tensor([1 / 5000, 0.125, 0.5], dtype=torch.float64)).tolist()
        assert got == pytest.approx([0.0813802024, 0.7560236144, 0.9186432719], abs=1e-10)

    def test_normalise_divides_by_own_max_and_clamps(self):
        hdr = torch.tensor([[[0.0, 1.0, 2.0], [4.0, 8.0, 8.0]]], dtype=torch.float64)
        torch.testing.assert_close(normalise_hdr(hdr), torch.from_numpy(mu_law_numpy(hdr.numpy() / 8.0)))
        # by a given maximum: values above it clamp to 1
        by_four = normalise_hdr(hdr, torch.tensor(4.0, dtype=torch.float64))
        torch.testing.assert_close(by_four, torch.from_numpy(mu_law_numpy(np.minimum(hdr.numpy() / 4.0, 1.0))))
        negative = normalise_hdr(torch.tensor([-1.0, 2.0], dtype=torch.float64))
        assert negative.tolist() == [0.0, 1.0]

    def test_images_dimmer_than_one(self):
        hdr = torch.tensor([0.0, 0.01, 0.25], dtype=torch.float64)
        torch.testing.assert_close(normalise_hdr(hdr), torch.from_numpy(mu_law_numpy(hdr.numpy() / 0.25)))

    @pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32])
    def test_all_zero_stays_zero_in_every_precision(self, dtype):
        out = normalise_hdr(torch.zeros(4, 4, 3, dtype=dtype))
        assert out.dtype == dtype and not out.isnan().any() and not out.any()

    def test_half_precision_is_computed_in_float32(self):
        hdr = torch.tensor([1e-4, 1.0, 60000.0], dtype=torch.float16)
        got = normalise_hdr(hdr)
        assert got.dtype == torch.float16
        expected = mu_law_numpy(hdr.double().numpy() / 60000.0)
        np.testing.assert_allclose(got.double().numpy(), expected, atol=1e-3)


class TestLdrMetricsAgainstScikitImage:
    @pytest.fixture
    def pair(self):
        rng = np.random.default_rng(21)
        target = rng.random((24, 20, 3))
        pred = np.clip(target + 0.05 * rng.standard_normal(target.shape), 0, 1)
        return pred, target

    def test_psnr(self, pair):
        pred, target = pair
        expected = peak_signal_noise_ratio(target, pred, data_range=1.0)
        assert psnr(torch.from_numpy(pred), torch.from_numpy(target)) == pytest.approx(expected, rel=1e-12)
        assert psnr(torch.from_numpy(pred).float(), torch.from_numpy(target).float()) == pytest.approx(
            expected, rel=1e-5
        )

    def test_psnr_by_hand(self):
        # one pixel of 25 off by 0.5: MSE = 0.25 / 25 = 0.01, PSNR = 20 dB; with data range 2, 26.02 dB
        target = torch.zeros(5, 5, 1)
        pred = target.clone()
        pred[2, 3] = 0.5
        assert psnr(pred, target) == pytest.approx(20.0, rel=1e-9)
        assert psnr(pred, target, data_range=2.0) == pytest.approx(20.0 + 20 * math.log10(2), rel=1e-9)

    def test_ssim(self, pair):
        pred, target = pair
        expected = skimage_ssim(pred, target)
        assert 0.3 < expected < 0.99
        assert ssim(torch.from_numpy(pred), torch.from_numpy(target)).item() == pytest.approx(expected, abs=1e-10)

    def test_ssim_map_mean_is_skimage_ssim(self, pair):
        pred, target = pair
        window_map = ssim_map(torch.from_numpy(pred), torch.from_numpy(target))
        assert window_map.shape == (24 - 10, 20 - 10, 3)
        assert window_map.mean().item() == pytest.approx(skimage_ssim(pred, target), abs=1e-10)

    @pytest.mark.parametrize("size", [(10, 30), (30, 10)])
    def test_ssim_needs_the_whole_window(self, size):
        with pytest.raises(ValueError, match="at least 11 pixels per side, got"):
            ssim_map(torch.rand(*size, 3), torch.rand(*size, 3))
        assert ssim_map(torch.rand(11, 11, 3), torch.rand(11, 11, 3)).shape == (1, 1, 3)

    def test_ssim_data_range(self, pair):
        pred, target = pair
        expected = structural_similarity(
            4 * pred,
            4 * target,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
            data_range=4.0,
            channel_axis=-1,
        )
        got = ssim(torch.from_numpy(4 * pred), torch.from_numpy(4 * target), data_range=4.0).item()
        assert got == pytest.approx(expected, abs=1e-10)

    def test_ssim_of_structure_only_difference(self):
        """Same mean and variance, other structure: SSIM is far from 1, PSNR-like metrics can miss it."""
        rng = np.random.default_rng(4)
        target = rng.random((16, 16, 1))
        pred = target[::-1].copy()
        assert ssim(torch.from_numpy(pred), torch.from_numpy(target)).item() == pytest.approx(
            skimage_ssim(pred, target), abs=1e-10
        )


class TestHdrPairWorkedByHand:
    """Ground truth 8 | 1 and prediction 4 | 1 (left | right halves).

    own_max: the prediction over its max is 1 | 1/4, mu-law 1 | ln 1251 / ln 5001 = 0.837313; the
    ground truth over its max is 1 | 1/8, mu-law 1 | ln 626 / ln 5001 = 0.756024, stored as 8 bits:
    round(192.786) / 255 = 193 / 255. Only the right half differs, so MSE = (0.837313 - 193/255)^2 / 2.
    gt_max: both over 8; the prediction is 1/2 | 1/8, the ground truth 1 | 1/8, so only the left
    half differs: MSE = (1 - ln 2501 / ln 5001)^2 / 2.
    """

    OWN_MAX_ERROR = math.log(1251) / LN_5001 - 193 / 255
    GT_MAX_ERROR = 1 - math.log(2501) / LN_5001

    def test_own_max_psnr(self):
        pred, gt = two_region_pair()
        expected = -10 * math.log10(self.OWN_MAX_ERROR**2 / 2)
        assert expected == pytest.approx(24.9001, abs=1e-4)
        assert hdr_metrics(pred, gt)["hdr_psnr"] == pytest.approx(expected, rel=1e-9)

    def test_gt_max_psnr(self):
        pred, gt = two_region_pair()
        expected = -10 * math.log10(self.GT_MAX_ERROR**2 / 2)
        assert expected == pytest.approx(24.8024, abs=1e-4)
        assert hdr_metrics(pred, gt)["hdr_psnr_gt_max"] == pytest.approx(expected, rel=1e-9)

    def test_tone_mapped_images(self):
        pred, gt = two_region_pair()
        own_pred, own_gt = tone_mapped_pair(pred, gt, "own_max")
        assert own_pred[0, 0, 0].item() == pytest.approx(1.0) and own_gt[0, 0, 0].item() == pytest.approx(1.0)
        assert own_pred[0, -1, 0].item() == pytest.approx(math.log(1251) / LN_5001, rel=1e-12)
        assert own_gt[0, -1, 0].item() == pytest.approx(193 / 255, rel=1e-12)
        gt_pred, gt_gt = tone_mapped_pair(pred, gt, "gt_max")
        assert gt_pred[0, 0, 0].item() == pytest.approx(math.log(2501) / LN_5001, rel=1e-12)
        assert gt_gt[0, 0, 0].item() == pytest.approx(1.0)
        assert gt_pred[0, -1, 0].item() == pytest.approx(gt_gt[0, -1, 0].item(), rel=1e-12)
        assert gt_gt[0, -1, 0].item() == pytest.approx(math.log(626) / LN_5001, rel=1e-12)

    def test_ssim_both_normalisations(self):
        pred, gt = two_region_pair()
        right = np.s_[:, 8:]
        own_pred, own_gt = np.ones((16, 16, 3)), np.ones((16, 16, 3))
        own_pred[right], own_gt[right] = math.log(1251) / LN_5001, 193 / 255
        gt_pred, gt_gt = np.full((16, 16, 3), math.log(626) / LN_5001), np.full((16, 16, 3), math.log(626) / LN_5001)
        gt_pred[:, :8], gt_gt[:, :8] = math.log(2501) / LN_5001, 1.0
        metrics = hdr_metrics(pred, gt)
        assert metrics["hdr_ssim"] == pytest.approx(skimage_ssim(own_pred, own_gt), abs=1e-10)
        assert metrics["hdr_ssim_gt_max"] == pytest.approx(skimage_ssim(gt_pred, gt_gt), abs=1e-10)
        assert metrics["hdr_ssim"] < 0.99 and metrics["hdr_ssim_gt_max"] < 0.99

    def test_float32_input_gives_the_same_figures(self):
        pred, gt = two_region_pair(torch.float32)
        metrics = hdr_metrics(pred, gt)
        assert all(type(value) is float for value in metrics.values())
        in_double = hdr_metrics(*two_region_pair(torch.float64))
        assert metrics["hdr_ssim"] == pytest.approx(in_double["hdr_ssim"], abs=1e-6)
        assert metrics["hdr_ssim_gt_max"] == pytest.approx(in_double["hdr_ssim_gt_max"], abs=1e-6)
        assert metrics["hdr_psnr"] == pytest.approx(-10 * math.log10(self.OWN_MAX_ERROR**2 / 2), rel=1e-5)
        assert metrics["hdr_psnr_gt_max"] == pytest.approx(-10 * math.log10(self.GT_MAX_ERROR**2 / 2), rel=1e-5)

    def test_order_matters(self):
        """Prediction and ground truth are not interchangeable: only the ground truth is quantised,
        and gt_max divides by the ground truth's maximum."""
        pred, gt = two_region_pair()
        forward, swapped = hdr_metrics(pred, gt), hdr_metrics(gt, pred)
        assert swapped["hdr_psnr"] != pytest.approx(forward["hdr_psnr"], abs=0.1)
        assert swapped["hdr_psnr_gt_max"] != pytest.approx(forward["hdr_psnr_gt_max"], abs=0.1)


class TestHdrMetricsOnTexturedImages:
    """A random HDR scene with a 1000:1 range against numpy + scikit-image references."""

    @pytest.fixture
    def pair(self):
        rng = np.random.default_rng(7)
        gt = np.exp(rng.uniform(np.log(0.05), np.log(50.0), (20, 18, 3)))
        pred = gt * np.exp(0.3 * rng.standard_normal(gt.shape)) * 0.7
        return pred, gt

    def test_against_references(self, pair):
        pred, gt = pair
        own_pred = mu_law_numpy(pred / pred.max())
        own_gt = np.round(mu_law_numpy(gt / gt.max()) * 255) / 255
        by_gt_pred = mu_law_numpy(np.clip(pred / gt.max(), 0, 1))
        by_gt_gt = mu_law_numpy(gt / gt.max())
        assert skimage_ssim(own_pred, own_gt) < 0.99 and skimage_ssim(by_gt_pred, by_gt_gt) < 0.99
        metrics = hdr_metrics(torch.from_numpy(pred), torch.from_numpy(gt))
        assert metrics["hdr_psnr"] == pytest.approx(peak_signal_noise_ratio(own_gt, own_pred, data_range=1.0), rel=1e-9)
        assert metrics["hdr_ssim"] == pytest.approx(skimage_ssim(own_pred, own_gt), abs=1e-9)
        assert metrics["hdr_psnr_gt_max"] == pytest.approx(
            peak_signal_noise_ratio(by_gt_gt, by_gt_pred, data_range=1.0), rel=1e-9
        )
        assert metrics["hdr_ssim_gt_max"] == pytest.approx(skimage_ssim(by_gt_pred, by_gt_gt), abs=1e-9)


class RecordingNetwork(torch.nn.Module):
    """Stands in for the LPIPS network (its weights are not on this machine): mean absolute
    difference of what it is given, and a record of the inputs."""

    def __init__(self):
        super().__init__()
        self.inputs = []

    def forward(self, a, b):
        self.inputs.append((a, b))
        return (a - b).abs().mean()


class TestLpipsInputs:
    def test_images_reach_the_network_as_nchw_in_minus_one_to_one(self):
        network = RecordingNetwork()
        pred = torch.rand(6, 5, 3)
        target = torch.zeros(6, 5, 3)
        distance = lpips_distance(network, pred, target)
        assert type(distance) is float
        a, b = network.inputs[0]
        assert a.shape == (1, 3, 6, 5)
        torch.testing.assert_close(a[0], pred.permute(2, 0, 1) * 2 - 1)
        torch.testing.assert_close(b, -torch.ones(1, 3, 6, 5))
        assert distance == pytest.approx(2 * pred.mean().item(), rel=1e-5)


class FakeLpipsPackage:
    """Stands in for the `lpips` package: records how the network is asked for."""

    def __init__(self, fail: bool = False):
        self.fail, self.requests = fail, []

    def LPIPS(self, **options):
        self.requests.append(options)
        if self.fail:
            raise OSError("no internet to download alexnet weights")
        return RecordingNetwork()


class TestLoadLpips:
    @pytest.fixture(autouse=True)
    def fresh_cache(self):
        load_lpips.cache_clear()
        yield
        load_lpips.cache_clear()

    def test_asks_for_the_pretrained_alexnet_quietly(self, monkeypatch):
        package = FakeLpipsPackage()
        monkeypatch.setitem(sys.modules, "lpips", package)
        assert isinstance(load_lpips(), RecordingNetwork)
        assert package.requests == [{"net": "alex", "verbose": False, "pretrained": True}]

    def test_missing_weights_are_reported_not_downloaded(self, monkeypatch):
        monkeypatch.setitem(sys.modules, "lpips", FakeLpipsPackage(fail=True))
        with pytest.raises(LpipsUnavailable, match="weights are not available locally"):
            load_lpips()
