import math

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from mono_hdr_plugin.core.losses import LOG_FLOOR, l1_dssim_loss, mse_loss, photometric_loss, scale_invariant_log_loss
from mono_hdr_plugin.core.metrics import (
    chroma_outliers,
    hdr_metrics,
    mu_law,
    normalise_hdr,
    psnr,
    source_metrics,
    source_region,
    ssim,
    ssim_map,
    ssim_map_reference,
    tone_mapped_pair,
)


class TestPsnr:
    def test_identical_is_inf(self):
        image = torch.rand(8, 8, 3)
        assert psnr(image, image) == math.inf

    def test_hand_computed(self):
        pred, target = torch.zeros(4, 4, 3), torch.full((4, 4, 3), 0.1)
        assert psnr(pred, target) == pytest.approx(20.0)

    def test_matches_skimage(self):
        rng = np.random.default_rng(0)
        a, b = rng.random((20, 24, 3)), rng.random((20, 24, 3))
        expected = peak_signal_noise_ratio(b, a, data_range=1)
        assert psnr(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(expected, rel=1e-9)

    def test_shape_mismatch_raises(self):
        with pytest.raises(ValueError, match="shapes differ"):
            psnr(torch.zeros(3, 3, 3), torch.zeros(3, 4, 3))


class TestSsim:
    @pytest.mark.parametrize("mapper", [ssim_map, ssim_map_reference], ids=["kernel", "torch"])
    @pytest.mark.parametrize("shape", [(32, 32, 3), (17, 40, 1), (11, 11, 3)])
    def test_matches_skimage_3dgs_settings(self, shape, mapper):
        rng = np.random.default_rng(1)
        a = rng.random(shape)
        b = np.clip(a + 0.2 * rng.standard_normal(shape), 0, 1)
        expected = structural_similarity(
            a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1
        )
        got = mapper(torch.from_numpy(a), torch.from_numpy(b)).mean().item()
        assert got == pytest.approx(expected, abs=1e-10)

    def test_identical_is_one(self):
        image = torch.rand(16, 16, 3, dtype=torch.float64)
        assert ssim(image, image).item() == pytest.approx(1.0)

    def test_too_small_raises(self):
        with pytest.raises(ValueError, match="at least 11"):
            ssim_map(torch.rand(8, 8, 3), torch.rand(8, 8, 3))

    def test_gradcheck(self):
        a = torch.rand(12, 12, 1, dtype=torch.float64, requires_grad=True)
        b = torch.rand(12, 12, 1, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: ssim(x, b), (a,))


class TestSsimKernel:
    """The fused C++ SSIM (`ssim_map` on the CPU with a constant target) against its torch twin."""

    @pytest.mark.parametrize("shape", [(40, 33, 3), (11, 11, 1), (12, 70, 3)])
    def test_map_and_gradient_match_the_twin(self, shape):
        generator = torch.Generator().manual_seed(sum(shape))
        pred = torch.rand(shape, generator=generator).requires_grad_()
        target = (pred.detach() + 0.1 * torch.randn(shape, generator=generator)).clamp(0, 1)
        upstream = torch.randn(shape[0] - 10, shape[1] - 10, shape[2], generator=generator)
        fused, reference = ssim_map(pred, target), ssim_map_reference(pred, target)
        torch.testing.assert_close(fused, reference, rtol=1e-5, atol=1e-5)
        (got,) = torch.autograd.grad(fused, pred, upstream)
        (expected,) = torch.autograd.grad(reference, pred, upstream)
        torch.testing.assert_close(got, expected, rtol=1e-4, atol=1e-5 * expected.abs().max().item())

    def test_gradcheck_in_double_away_from_the_border(self):
        pred = torch.rand(16, 13, 2, dtype=torch.float64, requires_grad=True)
        target = torch.rand(16, 13, 2, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: ssim_map(x, target, data_range=2.0), (pred,))

    def test_a_target_that_needs_a_gradient_gets_one(self):
        pred, target = torch.rand(14, 14, 3), torch.rand(14, 14, 3, requires_grad=True)
        ssim(pred, target).backward()
        assert target.grad is not None and target.grad.abs().sum() > 0

    def test_the_same_on_one_thread_and_two(self):
        pred, target = torch.rand(64, 48, 3, requires_grad=True), torch.rand(64, 48, 3)
        results = []
        for threads in (1, 2):
            previous = torch.get_num_threads()
            torch.set_num_threads(threads)
            try:
                value = ssim(pred, target)
                results.append((value, *torch.autograd.grad(value, pred)))
            finally:
                torch.set_num_threads(previous)
        for one, two in zip(*results, strict=True):
            torch.testing.assert_close(one, two)


class TestMuLaw:
    def test_endpoints_and_monotone(self):
        x = torch.tensor([0.0, 0.001, 0.5, 1.0])
        y = mu_law(x)
        assert y[0] == 0 and y[-1] == pytest.approx(1.0) and (y.diff() > 0).all()

    def test_normalise_all_zero_stays_zero(self):
        out = normalise_hdr(torch.zeros(4, 4, 3))
        assert torch.equal(out, torch.zeros(4, 4, 3))

    def test_normalise_is_scale_invariant(self):
        hdr = torch.rand(5, 5, 3) * 10
        torch.testing.assert_close(normalise_hdr(hdr), normalise_hdr(hdr * 1000))


class TestHdrMetrics:
    def test_own_max_ignores_scale_gt_max_does_not(self):
        gt = torch.rand(16, 16, 3) * 50
        scaled = gt * 0.25
        metrics = hdr_metrics(scaled, gt)
        assert metrics["hdr_psnr"] > 40  # only the GT's 8-bit quantisation differs
        assert metrics["hdr_psnr_gt_max"] < metrics["hdr_psnr"] - 10

    def test_gt_max_normalisation_by_ground_truth(self):
        gt = torch.rand(12, 12, 3) + 1.0
        pred, target = tone_mapped_pair(gt * 2, gt, "gt_max")
        torch.testing.assert_close(target, mu_law(gt / gt.max()))
        assert pred.max() == pytest.approx(1.0)  # clamped at the GT max

    def test_own_max_quantises_ground_truth_to_8_bit(self):
        gt = torch.rand(12, 12, 3) * 3
        _, target = tone_mapped_pair(gt, gt, "own_max")
        torch.testing.assert_close(target * 255, torch.round(target * 255))


class TestLosses:
    def test_l1_dssim_hand_computed(self):
        pred, target = torch.zeros(12, 12, 3), torch.full((12, 12, 3), 0.5)
        expected = 0.8 * 0.5 + 0.2 * (1 - ssim(pred, target))
        assert l1_dssim_loss(pred, target).item() == pytest.approx(expected.item())

    def test_mse(self):
        assert mse_loss(torch.zeros(3), torch.full((3,), 2.0)).item() == pytest.approx(4.0)

    def test_pixel_batches_fall_back_to_l1(self):
        pred, target = torch.full((10, 3), 0.5), torch.full((10, 3), 0.3)
        pred[0, 0] = 0.1  # |0.1 - 0.3| = 0.2 like the others: only a true difference gives 0.2 everywhere
        assert photometric_loss(pred, target, "l1_dssim").item() == pytest.approx(0.2)

    def test_zero_for_identical(self):
        image = torch.rand(12, 12, 3)
        assert photometric_loss(image, image, "l1_dssim").item() == pytest.approx(0.0, abs=1e-6)


class TestScaleInvariantLogLoss:
    def test_blind_to_the_level(self):
        target = torch.rand(50, 3, dtype=torch.float64) * 10 + 0.1
        assert scale_invariant_log_loss(target, target).item() == 0.0
        assert scale_invariant_log_loss(37.0 * target, target).item() == pytest.approx(0.0, abs=1e-3)

    def test_a_dead_channel_of_a_dim_pixel_costs_as_much_as_one_of_the_brightest(self):
        """On a 1e6 : 1 image one pixel's channel off by 10x: the relative term costs the same wherever the
        pixel lies; the mu-law over the maximum (L_hdr) barely sees it on the dim pixel."""
        target = torch.ones(100, 3, dtype=torch.float64)
        target[0] = 1e6  # the sun
        dim, bright = target.clone(), target.clone()
        dim[50, 0] /= 10
        bright[0, 0] /= 10
        # numpy, from the definition: d = log(p + f) - log(t + f), f = LOG_FLOOR * mean(t); median(d) = 0 here
        floor = LOG_FLOOR * target.numpy().mean()
        expected_dim = abs(np.log(0.1 + floor) - np.log(1 + floor)) / 300
        expected_bright = abs(np.log(1e5 + floor) - np.log(1e6 + floor)) / 300
        assert scale_invariant_log_loss(dim, target).item() == pytest.approx(expected_dim)
        assert scale_invariant_log_loss(bright, target).item() == pytest.approx(expected_bright, rel=1e-3)
        mu_law_dim = (normalise_hdr(dim) - normalise_hdr(target)).abs().mean().item()
        mu_law_bright = (normalise_hdr(bright) - normalise_hdr(target)).abs().mean().item()
        assert mu_law_dim < 0.01 * mu_law_bright

    def test_a_dead_channel_costs_a_bounded_gradient(self):
        target = torch.ones(10, 3, dtype=torch.float64)
        pred = target.clone().requires_grad_(True)
        with torch.no_grad():
            pred[3, 1] = 0.0
        scale_invariant_log_loss(pred, target).backward()
        assert torch.isfinite(pred.grad).all()
        # d/dp |log(p + f)| / 30 at p = 0 is 1 / (30 f), f = LOG_FLOOR * 1
        assert pred.grad[3, 1].item() == pytest.approx(-1 / (30 * LOG_FLOOR))

    def test_gradcheck(self):
        target = torch.rand(6, 3, dtype=torch.float64) + 0.5
        pred = (target * torch.exp(torch.randn(6, 3, dtype=torch.float64))).requires_grad_(True)
        assert torch.autograd.gradcheck(lambda p: scale_invariant_log_loss(p, target), (pred,))


class TestLpips:
    def test_skipped_with_a_clear_reason_when_unavailable(self, monkeypatch):
        import builtins

        from mono_hdr_plugin.core.metrics import LpipsUnavailable, load_lpips

        real_import = builtins.__import__

        def no_lpips(name, *args, **kwargs):
            if name == "lpips":
                raise ImportError("no module named lpips")
            return real_import(name, *args, **kwargs)

        load_lpips.cache_clear()
        monkeypatch.setattr(builtins, "__import__", no_lpips)
        with pytest.raises(LpipsUnavailable, match="LPIPS skipped"):
            load_lpips()
        load_lpips.cache_clear()


class TestSourceMetrics:
    """The brightest source's peak, on a 6 x 6 view with a 1-pixel sun of 1000 on a sky of 1."""

    @staticmethod
    def sunny_view():
        gt = torch.ones(6, 6, 3)
        gt[2, 3] = torch.tensor([1000.0, 900.0, 800.0])
        photo = (gt * 0.5).clamp(0, 1)
        return gt, photo

    def test_a_source_drawn_one_pixel_off_at_half_its_peak(self):
        gt, photo = self.sunny_view()
        pred = torch.ones(6, 6, 3)
        pred[3, 4] = torch.tensor([500.0, 450.0, 400.0])  # diagonal neighbour: inside the grown region
        ldr = photo.clone()
        ldr[2, 3] = 0.5  # the LDR render lost the clipped sun: half the photo's 1.0
        figures = source_metrics(pred, gt, ldr, photo)
        assert figures["hdr_peak_ratio"] == pytest.approx(0.5)
        assert figures["ldr_peak_ratio"] == pytest.approx(0.5 / 1.0)

    def test_a_lost_source_scores_near_zero(self):
        gt, photo = self.sunny_view()
        pred = torch.ones(6, 6, 3)
        pred[5, 0] = 1000.0  # bright, but two pixels and more away from the sun
        assert source_metrics(pred, gt, photo, photo)["hdr_peak_ratio"] == pytest.approx(1 / 1000)

    def test_the_region_holds_the_source_and_its_neighbours_only(self):
        gt, _ = self.sunny_view()
        region = source_region(gt)
        assert int(region.sum()) == 9 and bool(region[1:4, 2:5].all())


class TestChromaOutliers:
    def test_counts_pixels_whose_colour_is_off_whatever_their_level(self):
        gt = torch.tensor([0.2, 0.3, 0.5]).repeat(4, 5, 1)  # sky blue, 20 pixels
        photo = gt.clone()  # every pixel well exposed
        pred = 7.0 * gt  # another level, the same colour: never an outlier
        pred[0, 0] = torch.tensor([0.3, 0.6, 0.1])  # a green floater
        pred[1, 1] = torch.tensor([0.23, 0.3, 0.47])  # chromaticity off by 0.03: within the bound
        pred[2, 2] = torch.tensor([0.5, 0.2, 0.3])  # magenta
        assert chroma_outliers(pred, gt, photo) == pytest.approx(2 / 20)

    def test_only_pixels_the_photo_exposes_well_count(self):
        gt = torch.tensor([0.2, 0.3, 0.5]).repeat(3, 5, 1)
        photo = gt.clone()
        photo[0] = torch.tensor([0.01, 0.02, 0.04])  # buried in the dark: 5 pixels left out
        photo[1, :2] = 1.0  # clipped: 2 more left out
        pred = gt.clone()
        pred[0] = torch.tensor([1.0, 0.0, 0.0])  # wrong colours, but not counted
        pred[1, :2] = torch.tensor([1.0, 0.0, 0.0])
        pred[2, 0] = torch.tensor([0.5, 0.3, 0.2])  # counted, and wrong
        assert chroma_outliers(pred, gt, photo) == pytest.approx(1 / 8)
        assert math.isnan(chroma_outliers(pred, gt, torch.ones_like(photo)))
