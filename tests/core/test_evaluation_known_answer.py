"""`evaluate` and `mono-hdr eval` on a model whose renders are known exactly (known_render.py).

Every expected figure is computed here from the closed-form render with numpy and
scikit-image, view by view; the averages are then taken by hand: LDR per exposure over its
views, the headline LDR over the training exposures, HDR over cameras (one view each).
"""

import importlib.util
import json
import math

import numpy as np
import pytest
import torch
from known_render import KnownRenderConfig, camera_at, expected_render, ground_truth, known_scene, zero_method
from PIL import Image
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.exposure import ViewExposures, srgb_response
from mono_hdr_plugin.core.metrics import psnr
from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot, constant
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import read_exr
from mono_hdr_plugin.data.layouts import LAYOUTS
from mono_hdr_plugin.methods.base import MethodConfig
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.evaluation import evaluate
from mono_hdr_plugin.training.pipeline import Pipeline
from mono_hdr_plugin.training.trainer import build_trainer

LN_5001 = math.log(5001.0)
HDR_KEYS = (
    "hdr_psnr",
    "hdr_ssim",
    "hdr_psnr_gt_max",
    "hdr_ssim_gt_max",
    "hdr_psnr_aligned",
    "hdr_psnr_masked",
    "hdr_median_ratio",
    "hdr_peak_ratio",
    "ldr_peak_ratio",
    "chroma_outliers",
    "hdr_psnr_clipped",
    "hdr_psnr_unclipped",
    "clipped_fraction",
)
RADIANCE_KEYS = tuple(
    f"{against}{score}_{c}"
    for against in ("hdr_", "hdr_own_ldr_")
    for score in ("rank_correlation", "log_slope")
    for c in "rgb"
)


def mu_law(x: np.ndarray) -> np.ndarray:
    return np.log1p(5000.0 * x) / LN_5001


def ssim_3dgs(a: np.ndarray, b: np.ndarray) -> float:
    return structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0, channel_axis=-1
    )


def tone_mapped_own_max(hdr: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The GS evaluation's images: prediction over its own max, ground truth over its max in 8 bits."""
    return mu_law(hdr / hdr.max()), np.round(mu_law(gt / gt.max()) * 255) / 255


def median_log_ratio(a: np.ndarray, b: np.ndarray) -> float:
    """exp(median(log a - log b)) over the entries where both are positive."""
    usable = (a > 0) & (b > 0)
    return float(np.exp(np.median(np.log(a[usable]) - np.log(b[usable]))))


def well_exposed(photo: np.ndarray) -> np.ndarray:
    return ((photo > 0.05) & (photo < 0.95)).all(-1)


def scale_figures(hdr: np.ndarray, gt: np.ndarray, photo: np.ndarray) -> dict[str, float]:
    """Aligned and emitter-masked GT-max PSNR, and the median ratio, by their definitions."""
    peaks = gt.max(-1).ravel()
    left_out = int(np.ceil(0.001 * peaks.size))  # 256 pixels: the single brightest
    keep = np.ones(peaks.size, bool)
    keep[np.argsort(peaks)[-left_out:]] = False
    keep = keep.reshape(gt.shape[:2])
    aligned = hdr * median_log_ratio(gt[keep], hdr[keep])
    by_gt = mu_law(gt / gt.max())
    return {
        "hdr_psnr_aligned": peak_signal_noise_ratio(by_gt, mu_law(np.clip(aligned / gt.max(), 0, 1)), data_range=1.0),
        "hdr_psnr_masked": peak_signal_noise_ratio(
            by_gt[keep], mu_law(np.clip(hdr / gt.max(), 0, 1))[keep], data_range=1.0
        ),
        "hdr_median_ratio": median_log_ratio(hdr[well_exposed(photo)], gt[well_exposed(photo)]),
    }


def source_figures(hdr: np.ndarray, gt: np.ndarray, ldr: np.ndarray, photo: np.ndarray) -> dict[str, float]:
    """Peak ratios on the ground truth's brightest pixels (>= half its max) and their 8 neighbours, and the
    fraction of the pixels the photo exposes well whose chromaticity is off by more than 0.05."""
    bright = gt.max(-1) >= 0.5 * gt.max()
    region = np.zeros_like(bright)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            shifted = np.zeros_like(bright)
            h, w = bright.shape
            shifted[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = bright[
                max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
            ]
            region |= shifted
    gt_sum = gt.sum(-1)
    counted = well_exposed(photo) & (gt_sum > 0)
    chroma_gt = gt[counted] / gt_sum[counted, None]
    chroma_pred = hdr[counted] / np.maximum(hdr.sum(-1)[counted, None], 1e-12)
    return {
        "hdr_peak_ratio": hdr.max(-1)[region].max() / gt.max(),
        "ldr_peak_ratio": ldr.max(-1)[region].max() / photo.max(-1)[region].max(),
        "chroma_outliers": float((np.abs(chroma_pred - chroma_gt).max(-1) > 0.05).mean()),
    }


def expected_calibration(views, method: str) -> float:
    """The radiance scale fitted on training `views` (all of them, whole images): the median of
    gt / hdr over the values of pixels their photos expose well."""
    gt, hdr = [], []
    for view in views:
        exposed = well_exposed(view.image.double().numpy())
        gt.append(view.hdr.double().numpy()[exposed])
        hdr.append(expected_render(view.camera, method)[1][exposed])
    return median_log_ratio(np.concatenate(gt), np.concatenate(hdr))


def expected_row(
    view, method: str, scored_hdr: bool, brightness: float = 1.0, radiance_scale: float = 1.0
) -> dict[str, float]:
    """The figures of one view, from the closed-form render (its HDR times `radiance_scale`) and the
    view's ground truth; the LDR render is scored clipped to [0, 1]."""
    ldr, hdr = expected_render(view.camera, method, brightness)
    hdr = hdr * radiance_scale
    ldr = np.clip(ldr, 0.0, 1.0)
    photo = view.image.double().numpy()
    row = {"ldr_psnr": peak_signal_noise_ratio(photo, ldr, data_range=1.0), "ldr_ssim": ssim_3dgs(ldr, photo)}
    if scored_hdr:
        gt = view.hdr.double().numpy()
        own_pred, own_gt = tone_mapped_own_max(hdr, gt)
        by_gt_pred, by_gt_gt = mu_law(np.clip(hdr / gt.max(), 0, 1)), mu_law(gt / gt.max())
        row.update(
            hdr_psnr=peak_signal_noise_ratio(own_gt, own_pred, data_range=1.0),
            hdr_ssim=ssim_3dgs(own_pred, own_gt),
            hdr_psnr_gt_max=peak_signal_noise_ratio(by_gt_gt, by_gt_pred, data_range=1.0),
            hdr_ssim_gt_max=ssim_3dgs(by_gt_pred, by_gt_gt),
            **scale_figures(hdr, gt, photo),
            **source_figures(hdr, gt, ldr, photo),
        )
        clipped = (photo >= 1.0).any(-1)
        for key, part in (("hdr_psnr_clipped", clipped), ("hdr_psnr_unclipped", ~clipped)):
            error = np.mean((by_gt_pred[part] - by_gt_gt[part]) ** 2) if part.any() else math.nan
            row[key] = math.nan if math.isnan(error) else (math.inf if error == 0 else -10 * math.log10(error))
        row["clipped_fraction"] = float(clipped.mean())
    return row


def known_pipeline(scene, method: str, brightness: float = 1.0) -> Pipeline:
    pipeline = Pipeline.create(
        "known-render", KnownRenderConfig(brightness), MethodConfig(method=method), scene.scene_info()
    )
    zero_method(pipeline)
    return pipeline


def assert_rows(
    got: list[dict], views: list, method: str, hdr_views: set[tuple[int, float]], brightness: float = 1.0
) -> list[dict]:
    """`got` lists exactly `views` in order, each with its known figures; returns the expected rows."""
    assert [(r["view_id"], r["exposure"]) for r in got] == [(v.view_id, v.exposure) for v in views]
    expected = []
    for row, view in zip(got, views):
        scored = (view.view_id, view.exposure) in hdr_views
        want = expected_row(view, method, scored, brightness)
        assert row["view"] == view.stem
        assert all(type(row[key]) is float for key in want), "figures must be plain floats (JSON)"
        scores = {k for k in row if k not in ("view", "view_id", "exposure", "ldr_psnr", "ldr_ssim", "lpips_ldr")}
        # the scores against the photo and the model's own LDR (RADIANCE_KEYS) need no ground truth:
        # tests/core/test_hdr_prior.py
        assert scores - {"lpips_hdr", *RADIANCE_KEYS} == (set(HDR_KEYS) if scored else set()), row["view"]
        for key, value in want.items():
            assert row[key] == pytest.approx(value, rel=2e-5, abs=1e-6, nan_ok=True), (row["view"], key)
        expected.append(want)
    return expected


def mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)


class TestEvaluateKnownAnswer:
    def test_mono_scores_training_exposures_and_one_hdr_per_camera(self):
        scene = known_scene()
        metrics = evaluate(known_pipeline(scene, "mono"), scene)
        test = {(v.view_id, v.exposure): v for v in scene.test}
        # exposure 8 is not a training exposure: Mono-HDR's LDR branch cannot render it
        views = [test[key] for key in [(3, 2.0), (1, 0.5), (1, 2.0), (2, 0.5), (0, 0.5)]]
        hdr_views = {(3, 2.0), (1, 0.5), (0, 0.5)}  # camera 2 has no HDR ground truth
        rows = assert_rows(metrics["views"], views, "mono", hdr_views)
        at_half = mean(r["ldr_psnr"] for r, v in zip(rows, views) if v.exposure == 0.5)
        at_two = mean(r["ldr_psnr"] for r, v in zip(rows, views) if v.exposure == 2.0)
        assert metrics["ldr_psnr_per_exposure"] == pytest.approx({"0.5": at_half, "2": at_two}, rel=2e-5)
        # the headline weighs each training exposure equally, not each view
        assert metrics["ldr_psnr"] == pytest.approx((at_half + at_two) / 2, rel=2e-5)
        assert metrics["ldr_psnr"] != pytest.approx(mean(r["ldr_psnr"] for r in rows), rel=1e-4)
        ssim_half = mean(r["ldr_ssim"] for r, v in zip(rows, views) if v.exposure == 0.5)
        ssim_two = mean(r["ldr_ssim"] for r, v in zip(rows, views) if v.exposure == 2.0)
        assert metrics["ldr_ssim_per_exposure"] == pytest.approx({"0.5": ssim_half, "2": ssim_two}, rel=2e-5)
        assert metrics["ldr_ssim"] == pytest.approx((ssim_half + ssim_two) / 2, rel=2e-5)
        for key in HDR_KEYS:
            assert metrics[key] == pytest.approx(mean(r[key] for r in rows if key in r), rel=2e-5), key
        peaks = [r["hdr_peak_ratio"] for r in rows if "hdr_peak_ratio" in r]
        worst = peaks[int(np.argmax([abs(math.log(p)) for p in peaks]))]
        assert metrics["hdr_peak_ratio_worst"] == pytest.approx(worst, rel=2e-5)
        assert metrics["test_views"] == 4
        assert (metrics["backbone"], metrics["method"], metrics["scene"]) == ("known-render", "mono", "known-answer")

    def test_max_eval_views_takes_the_lowest_camera_ids(self):
        scene = known_scene()
        metrics = evaluate(known_pipeline(scene, "mono"), scene, max_eval_views=2)
        test = {(v.view_id, v.exposure): v for v in scene.test}
        views = [test[key] for key in [(1, 0.5), (1, 2.0), (0, 0.5)]]
        rows = assert_rows(metrics["views"], views, "mono", {(1, 0.5), (0, 0.5)})
        assert metrics["test_views"] == 2
        assert metrics["ldr_psnr_per_exposure"] == pytest.approx(
            {"0.5": (rows[0]["ldr_psnr"] + rows[2]["ldr_psnr"]) / 2, "2": rows[1]["ldr_psnr"]}, rel=2e-5
        )
        assert metrics["hdr_psnr"] == pytest.approx((rows[0]["hdr_psnr"] + rows[2]["hdr_psnr"]) / 2, rel=2e-5)

    @pytest.mark.parametrize("method", ["hdr-gs", "hdr-nerf"])
    def test_baselines_render_every_exposure_but_headline_the_trained_ones(self, method):
        scene = known_scene()
        metrics = evaluate(known_pipeline(scene, method), scene)
        # every test view, in list order; HDR from the first view of each camera that lists one
        rows = assert_rows(metrics["views"], scene.test, method, {(3, 2.0), (1, 8.0), (0, 0.5)})
        by_exposure = {
            e: mean(r["ldr_psnr"] for r, v in zip(rows, scene.test) if v.exposure == e) for e in (0.5, 2.0, 8.0)
        }
        assert metrics["ldr_psnr_per_exposure"] == pytest.approx(
            {"0.5": by_exposure[0.5], "2": by_exposure[2.0], "8": by_exposure[8.0]}, rel=2e-5
        )
        assert metrics["ldr_psnr"] == pytest.approx((by_exposure[0.5] + by_exposure[2.0]) / 2, rel=2e-5)
        for key in HDR_KEYS:
            assert metrics[key] == pytest.approx(mean(r[key] for r in rows if key in r), rel=2e-5), key
        assert metrics["test_views"] == 4

    def test_no_hdr_ground_truth_reports_none(self):
        scene = known_scene()
        for item in scene.test:
            item.hdr = None
        metrics = evaluate(known_pipeline(scene, "mono"), scene)
        assert all(metrics[key] is None for key in HDR_KEYS)
        # only the scores against the photo itself remain (no ground truth needed)
        assert not any(key.startswith("hdr_") and key not in RADIANCE_KEYS for row in metrics["views"] for key in row)

    def test_no_test_view_at_a_training_exposure_is_an_error(self):
        scene = known_scene()
        scene.test = [v for v in scene.test if v.exposure == 8.0]
        with pytest.raises(ValueError, match="no test view at a training exposure"):
            evaluate(known_pipeline(scene, "mono"), scene)

    def test_ldr_beyond_one_is_scored_clipped(self):
        scene = known_scene()
        metrics = evaluate(known_pipeline(scene, "mono", brightness=1.6), scene)
        test = {(v.view_id, v.exposure): v for v in scene.test}
        views = [test[key] for key in [(3, 2.0), (1, 0.5), (1, 2.0), (2, 0.5), (0, 0.5)]]
        rows = assert_rows(metrics["views"], views, "mono", {(3, 2.0), (1, 0.5), (0, 0.5)}, brightness=1.6)
        assert rows[0]["ldr_psnr"] < 15  # the render is far off, and clipped it is less so

    def test_views_of_unknown_exposure_are_fitted_to_their_photo(self):
        scene = known_scene()
        pipeline = known_pipeline(scene, "mono")
        pipeline.exposures = ViewExposures(torch.zeros(len(scene.train)), 1, 2.0, srgb_response(), learn=False)
        scene.metadata["unknown_exposures"] = [v.name for v in scene.test if v.exposure == 2.0]
        metrics = evaluate(pipeline, scene)
        fitted = [
            (row, v)
            for row in metrics["views"]
            for v in scene.test
            if (v.view_id, v.exposure) == (row["view_id"], row["exposure"]) and v.exposure == 2.0
        ]
        assert metrics["ldr_exposure_fitted"] == len(fitted) == 2
        with pipeline.evaluating():
            for row, view in fitted:  # fitted: at least as close to its photo as at the listed (placeholder) time
                listed = pipeline.render(view.camera, view.exposure).ldr
                assert row["ldr_psnr"] >= psnr(listed, view.image) - 1e-9

    def test_renders_written_once_per_camera(self, tmp_path):
        scene = known_scene()
        evaluate(known_pipeline(scene, "mono", brightness=1.6), scene, render_dir=tmp_path)
        stems = ["cam3_t2", "cam1_t1", "cam0_t1"]
        assert sorted(path.name for path in tmp_path.iterdir()) == sorted(
            f"{stem}{suffix}" for stem in stems for suffix in ("_ldr.png", "_hdr.exr", "_hdr_mulaw.png")
        )
        test = {v.stem: v for v in scene.test}
        for stem in stems:
            ldr, hdr = expected_render(test[stem].camera, "mono", brightness=1.6)
            np.testing.assert_allclose(read_exr(tmp_path / f"{stem}_hdr.exr"), hdr, rtol=1e-6)
            ldr_png = np.asarray(Image.open(tmp_path / f"{stem}_ldr.png"), dtype=np.float64)
            np.testing.assert_allclose(ldr_png, np.round(np.clip(ldr, 0, 1) * 255), atol=1)
            mu_png = np.asarray(Image.open(tmp_path / f"{stem}_hdr_mulaw.png"), dtype=np.float64)
            np.testing.assert_allclose(mu_png, np.round(mu_law(hdr / hdr.max()) * 255), atol=1)

    def test_lpips_of_both_images(self, monkeypatch):
        """With an LPIPS network (here one that measures mean absolute difference, as the real
        weights are not on this machine) each view gets LDR and HDR distances, averaged like the rest."""
        network = lambda a, b: (a - b).abs().mean()  # noqa: E731 - a one-line stand-in for the network
        monkeypatch.setattr("mono_hdr_plugin.training.evaluation.load_lpips", lambda: network)
        scene = known_scene()
        metrics = evaluate(known_pipeline(scene, "mono"), scene)
        expected_ldr, expected_hdr = [], []
        for row in metrics["views"]:
            view = next(v for v in scene.test if (v.view_id, v.exposure) == (row["view_id"], row["exposure"]))
            ldr, hdr = expected_render(view.camera, "mono")
            expected_ldr.append(2 * np.abs(ldr - view.image.double().numpy()).mean())
            assert row["lpips_ldr"] == pytest.approx(expected_ldr[-1], rel=1e-4)
            if "hdr_psnr" in row:
                expected_hdr.append(
                    2 * np.abs(np.subtract(*tone_mapped_own_max(hdr, view.hdr.double().numpy()))).mean()
                )
                assert row["lpips_hdr"] == pytest.approx(expected_hdr[-1], rel=1e-4)
            else:
                assert "lpips_hdr" not in row
        assert metrics["lpips_ldr"] == pytest.approx(mean(expected_ldr), rel=1e-4)
        assert metrics["lpips_hdr"] == pytest.approx(mean(expected_hdr), rel=1e-4)
        assert "lpips_skipped" not in metrics

    @pytest.mark.skipif(importlib.util.find_spec("lpips") is not None, reason="the lpips package is installed")
    def test_lpips_unavailable_is_said(self):
        scene = known_scene()
        metrics = evaluate(known_pipeline(scene, "mono"), scene)
        assert metrics["lpips_ldr"] is None and metrics["lpips_hdr"] is None
        assert metrics["lpips_skipped"].startswith("LPIPS skipped")


def captured_known_scene() -> CapturedScene:
    """Six cameras, each photographed at 0.5, 2 and 8 s, with HDR ground truth."""
    views = []
    for view_id in range(6):
        camera = camera_at(0.5 * view_id)
        shots = [
            Shot(exposure, constant(ground_truth(camera, 10 * view_id + e)[0].numpy()), f"{view_id}_{e}")
            for e, exposure in enumerate((0.5, 2.0, 8.0))
        ]
        views.append(
            CapturedView(
                view_id=view_id,
                camera=camera,
                split="test",
                shots=shots,
                hdr=constant(ground_truth(camera, view_id)[1].numpy()),
                name=str(view_id),
            )
        )
    return CapturedScene(
        name="known-answer", views=views, bounds_min=torch.full((3,), -4.0), bounds_max=torch.full((3,), 4.0)
    )


class TestEvalCommandKnownAnswer:
    def test_train_then_eval_report_the_known_figures(self, tmp_path):
        data = tmp_path / "data"
        LAYOUTS.get("hdr-gs").write(captured_known_scene(), data)
        config = train_config_for(KnownRenderConfig)(
            backbone=KnownRenderConfig(),
            out=tmp_path / "run",
            quiet=True,
            max_steps=0,
            save_renders=False,
            max_eval_views=2,
            data=DataConfig(data=data, protocol="single"),
        )
        trainer = build_trainer(config, "known-render")
        zero_method(trainer.pipeline)
        trained = trainer.train()
        main(
            [
                "eval",
                "--checkpoint",
                str(trainer.checkpoint_path()),
                "--out",
                str(tmp_path / "eval"),
                "--no-save-renders",
            ]
        )
        evaluated = json.loads((tmp_path / "eval" / "metrics.json").read_text())
        # the hdr-gs layout puts odd cameras in the test split; single protocol: all at t3 = 2 s
        views = [v for v in trainer.scene.test if v.view_id in (1, 3)]
        assert [(v.view_id, v.exposure) for v in views] == [(1, 2.0), (3, 2.0)]
        scale = expected_calibration(trainer.scene.train, "mono")
        assert abs(math.log(scale)) > 0.5  # the ground truth is 3-8x the render: the calibration must show
        expected = [expected_row(v, "mono", scored_hdr=True, radiance_scale=scale) for v in views]
        for metrics in (trained, evaluated):
            assert [row["view"] for row in metrics["views"]] == [v.stem for v in views]
            for row, want in zip(metrics["views"], expected):
                for key, value in want.items():
                    assert row[key] == pytest.approx(value, rel=2e-5, abs=1e-6, nan_ok=True), (row["view"], key)
            for key in ("ldr_psnr", "ldr_ssim", *HDR_KEYS):
                values = [w[key] for w in expected if not math.isnan(w[key])]  # NaN: no pixel of that kind
                assert metrics[key] == pytest.approx(mean(values), rel=2e-5), key
            assert metrics["test_views"] == 2
            assert metrics["radiance_scale"] == pytest.approx(scale, rel=1e-5)
            assert metrics["radiance_units"] == "ground_truth"
        assert evaluated["steps"] == 0
