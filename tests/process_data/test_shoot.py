"""The simulated photographer, and process-data turning its brackets into HDR views."""

import json
import math
from dataclasses import replace
from fractions import Fraction

import numpy as np
import pytest
import torch
from PIL import Image
from process_data_photos import textured_scene

from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data
from mono_hdr_plugin.apps.studio.capture import capture
from mono_hdr_plugin.apps.studio.render import render_scene
from mono_hdr_plugin.apps.studio.shoot import ShootConfig, metered_exposure, shoot, third_stop
from mono_hdr_plugin.core.metrics import hdr_metrics
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.io import read_exr
from mono_hdr_plugin.data.loading import captured_scene, downscale_image, load_scene
from mono_hdr_plugin.data.photos.exif import read_exif

SHOOT = ShootConfig(views="all", bracket_every=4, bracket_stops=(-2.0, 0.0, 2.0))
"""16 viewpoints, brackets of three at four of them: 24 photos."""


@pytest.fixture(scope="module")
def scene(studio_cache, texture):
    return textured_scene(texture, views=16, resolution=192)


@pytest.fixture(scope="module")
def photos(scene, tmp_path_factory):
    return shoot(scene, tmp_path_factory.mktemp("shoot") / "photos", SHOOT)


class TestMetering:
    def test_geometric_mean_of_lit_pixels(self):
        radiance = np.zeros((4, 4, 3), np.float32)
        radiance[:2] = 0.5
        radiance[:1] = 2.0  # geometric mean of 2.0 and 0.5 is 1.0; the empty half does not count
        assert metered_exposure(radiance, 0.18) == pytest.approx(0.18)

    def test_nothing_lit(self):
        assert metered_exposure(np.zeros((4, 4, 3), np.float32), 0.18) == 1.0


class TestShoot:
    def test_brackets_and_singles(self, photos):
        assert len(photos.shots) == 24 and photos.held_out == []
        assert photos.bracket_views == [0, 4, 8, 12]
        for bracket in range(4):
            members = [shot for shot in photos.shots if shot.bracket == bracket]
            ratios = [shot.exposure / members[1].exposure for shot in members]
            assert [shot.stops for shot in members] == [-2.0, 0.0, 2.0]
            assert ratios == pytest.approx([0.25, 1.0, 4.0], rel=0.01)  # third-stop rounding of each time

    def test_exif_holds_the_truth(self, photos):
        times = []
        for shot in photos.shots:
            with Image.open(photos.folder / shot.file) as image:
                exif = read_exif(image)
            assert exif.exposure_time == pytest.approx(shot.exposure, rel=1e-6)
            assert exif.iso == 100 and exif.f_number == pytest.approx(2.8)
            assert exif.auto_bracket == (shot.bracket is not None)
            times.append(exif.timestamp)
        assert all(later > earlier for earlier, later in zip(times, times[1:]))

    def test_auto_exposure_follows_the_view(self, scene, photos):
        radiance = render_scene(scene).radiance
        singles = [shot for shot in photos.shots if shot.bracket is None]
        assert len({shot.exposure for shot in singles}) > 3  # the camera meters every view
        for shot in singles:
            metered = metered_exposure(radiance[shot.view] * np.float32(SHOOT.brightness), SHOOT.metering_key)
            assert abs(math.log2(shot.exposure / metered)) < 4 * SHOOT.metering_jitter + 1 / 6

    def test_photo_is_the_capture_of_its_exposure(self, scene, photos):
        shot = photos.shots[5]
        with Image.open(photos.folder / shot.file) as image:
            pixels = np.asarray(image, np.float32) / 255
        radiance = render_scene(scene).radiance[shot.view] * np.float32(SHOOT.brightness)

        def error(exposure):  # on 4 x 4 block means, which JPEG's halved chroma resolution keeps
            same = capture(radiance, exposure, scene.effects + ("noise",), scene.capture, seed=shot.seed)
            return np.abs(downscale_image(pixels, 4, "jpeg") - downscale_image(same, 4, "capture")).mean()

        assert error(shot.exposure) < 0.01
        assert error(shot.exposure * 2 ** (1 / 3)) > 3 * error(shot.exposure)  # a third of a stop shows

    def test_without_exposure_exif(self, scene, tmp_path):
        result = shoot(scene, tmp_path / "photos", replace(SHOOT, exposure_exif=False, bracket_every=0))
        with Image.open(result.folder / result.shots[0].file) as image:
            exif = read_exif(image)
        assert exif.exposure_time is None and exif.iso is None and not exif.auto_bracket
        assert exif.timestamp is not None and exif.focal_35mm is not None

    def test_third_stops(self):
        assert third_stop(1 / 60) == Fraction(2 ** (-18 / 3)).limit_denominator(1_000_000)
        assert third_stop(0.5) == Fraction(1, 2)

    def test_training_views_only(self, scene, tmp_path):
        result = shoot(scene, tmp_path / "photos", replace(SHOOT, views="train", bracket_every=0))
        assert [shot.view for shot in result.shots] == list(range(0, 16, 2))
        assert result.held_out == list(range(1, 16, 2))


def merged_psnr(out, report, photos, scene) -> list[float]:
    """HDR PSNR of each merge on 4 x 4 block means: JPEG's halved chroma resolution cannot hold the
    pixel-sized colour noise of this texture (25-30 dB per pixel even with the true response)."""
    radiance = render_scene(scene).radiance
    views = {shot.file: shot.view for shot in photos.shots}
    scores = []
    for hdr_view in report.hdr_views:
        merged = downscale_image(read_exr(out / "exr" / f"{hdr_view.name.split('_')[0]}.exr"), 4, "merged")
        truth = downscale_image(radiance[views[hdr_view.sources[0]]], 4, "truth")
        scores.append(hdr_metrics(torch.from_numpy(merged), torch.from_numpy(truth))["hdr_psnr"])
    return scores


@pytest.fixture(scope="module")
def processed_shoot(photos, tmp_path_factory):
    out = tmp_path_factory.mktemp("shoot-data") / "dataset"
    return process_data(
        ProcessDataConfig(images=photos.folder, out=out, camera_model="SIMPLE_PINHOLE", num_threads=2)
    ), out


class TestProcessBrackets:
    def test_each_bracket_is_one_hdr_view(self, processed_shoot, photos):
        report, out = processed_shoot
        expected = [[shot.file for shot in photos.shots if shot.bracket == b] for b in range(4)]
        assert [hdr_view.sources for hdr_view in report.hdr_views] == expected
        assert len(report.views) == 16 and len(list((out / "exr").iterdir())) == 4
        assert sorted(p.name for p in (out / "images").iterdir()) == sorted(p.name for p in report.views)

    def test_merged_hdr_matches_the_truth(self, processed_shoot, photos, scene):
        report, out = processed_shoot
        assert min(merged_psnr(out, report, photos, scene)) > 38
        assert all(hdr_view.dynamic_range_stops > 4 for hdr_view in report.hdr_views)

    def test_the_metered_photo_is_the_view(self, processed_shoot, photos):
        report, _ = processed_shoot
        metered = {shot.file for shot in photos.shots if shot.bracket is not None and shot.stops == 0.0}
        assert {photo.source for photo in report.views if photo.bracket is not None} == metered

    def test_brackets_train_and_exposures_load(self, processed_shoot, photos):
        report, out = processed_shoot
        data = load_scene(DataConfig(data=out))
        assert {view.name for view in data.train if view.hdr is not None} == {h.name for h in report.hdr_views}
        assert all(view.hdr is None for view in data.test) and len(data.test) == len(report.test_views) == 2
        truth = {shot.file: shot.exposure for shot in photos.shots}
        sources = {photo.name: photo.source for photo in report.photos}
        for view in data.train + data.test:
            assert view.exposure == pytest.approx(truth[sources[view.name]], rel=1e-6)
        assert data.metadata["unknown_exposures"] == []

    def test_response_is_recorded(self, processed_shoot):
        report, out = processed_shoot
        response = json.loads((out / "camera_response.json").read_text())
        assert "recovered from 4 bracket set(s)" in report.response
        linear = np.array(response["linear_rgb"])
        assert linear.shape == (256, 3) and (np.diff(linear, axis=0) > 0).all()


@pytest.fixture(scope="module")
def unknown(scene, tmp_path_factory):
    """The same shoot without exposure EXIF, through process-data."""
    folder = tmp_path_factory.mktemp("no-exif")
    result = shoot(scene, folder / "photos", replace(SHOOT, exposure_exif=False))
    report = process_data(
        ProcessDataConfig(images=result.folder, out=folder / "dataset", camera_model="SIMPLE_PINHOLE", num_threads=2)
    )
    return result, report, folder / "dataset"


class TestProcessWithoutExposureExif:
    def test_exposures_unknown_and_flagged_for_learning(self, unknown):
        _, report, out = unknown
        assert not report.exposures_known and report.exposure_range is None
        assert set(json.loads((out / "exposures.json").read_text()).values()) == {None}
        scene = captured_scene(DataConfig(data=out))
        assert sorted(scene.metadata["unknown_exposures"]) == sorted(p.name for p in report.views)
        assert {shot.exposure for view in scene.views for shot in view.shots} == {1.0}

    def test_bracket_ratios_measured_from_the_pixels(self, unknown):
        photos, report, _ = unknown
        truth = {shot.file: shot.exposure for shot in photos.shots}
        assert len(report.hdr_views) == 4
        for hdr_view in report.hdr_views:
            assert hdr_view.exposures_estimated
            true = np.array([truth[name] for name in hdr_view.sources])
            np.testing.assert_allclose(np.array(hdr_view.exposures) / hdr_view.exposures[0], true / true[0], rtol=0.03)

    def test_merged_hdr_matches_the_truth(self, unknown, scene):
        photos, report, out = unknown
        assert min(merged_psnr(out, report, photos, scene)) > 36
