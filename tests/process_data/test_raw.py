"""RAW photos through rawpy: linear pixels and metadata, bad files, and process-data on a RAW shoot."""

import json
import os
from fractions import Fraction

import numpy as np
import pytest
from process_data_photos import textured_scene
from raw_files import write_dng

from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data
from mono_hdr_plugin.apps.studio.render import render_scene
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_exr, read_image
from mono_hdr_plugin.data.photos.raw import decode, encode, read_raw


def smooth_image(height: int = 64, width: int = 96) -> np.ndarray:
    yy, xx = np.mgrid[0:height, 0:width] / np.array([height, width])[:, None, None]
    return np.stack([0.2 + 0.5 * xx, 0.3 + 0.4 * yy, 0.6 - 0.4 * xx * yy], -1)


class TestReadRaw:
    def test_linear_pixels_and_exposure(self, tmp_path):
        truth = smooth_image()
        pixels, metadata = read_raw(write_dng(tmp_path / "a.dng", truth, exposure=Fraction(1, 60), f_number=4.0))
        assert pixels.shape == truth.shape and pixels.dtype == np.float32
        # Demosaicing interpolates: a smooth image comes back within the 14-bit steps, borders aside.
        np.testing.assert_allclose(pixels[4:-4, 4:-4], truth[4:-4, 4:-4], atol=2e-3)
        assert metadata.exposure_time == pytest.approx(1 / 60, rel=1e-6)
        assert metadata.f_number == pytest.approx(4.0, rel=1e-6)

    def test_pixels_scale_with_the_light(self, tmp_path):
        truth = smooth_image() * 0.25
        dim, _ = read_raw(write_dng(tmp_path / "dim.dng", truth))
        bright, _ = read_raw(write_dng(tmp_path / "bright.dng", truth * 3))
        ratio = bright[4:-4, 4:-4] / dim[4:-4, 4:-4]
        assert np.median(ratio) == pytest.approx(3.0, rel=2e-3)

    def test_missing_exposure_is_none(self, tmp_path):
        _, metadata = read_raw(write_dng(tmp_path / "a.dng", smooth_image()))
        assert metadata.exposure_time is None and metadata.timestamp is None

    @pytest.mark.parametrize("content", [b"", b"not a raw file at all" * 10])
    def test_rejected_file_names_the_file(self, tmp_path, content):
        path = tmp_path / "IMG_0001.CR2"
        path.write_bytes(content)
        with pytest.raises(DatasetError, match=r"IMG_0001.CR2: LibRaw cannot read this RAW file"):
            read_raw(path)

    def test_a_folder_name_that_is_not_utf8(self, tmp_path):
        """POSIX takes any bytes in a name; LibRaw takes UTF-8 paths only, so the file is passed open."""
        folder = tmp_path / os.fsdecode(b"caf\xe9-\xff")
        folder.mkdir()
        truth = smooth_image()
        pixels, metadata = read_raw(write_dng(folder / "a.dng", truth, exposure=Fraction(1, 60)))
        np.testing.assert_allclose(pixels[4:-4, 4:-4], truth[4:-4, 4:-4], atol=2e-3)
        assert metadata.exposure_time == pytest.approx(1 / 60, rel=1e-6)

    def test_truncated_dng_names_the_file(self, tmp_path):
        path = write_dng(tmp_path / "cut.dng", smooth_image())
        path.write_bytes(path.read_bytes()[:400])
        with pytest.raises(DatasetError, match="cut.dng: LibRaw cannot read"):
            read_raw(path)


class TestResponse:
    def test_srgb_round_trip_and_known_value(self):
        linear = np.linspace(0, 1, 11)[:, None, None] * np.ones((1, 1, 3))
        np.testing.assert_allclose(decode(encode(linear, "srgb"), "srgb"), linear, atol=1e-6)
        # sRGB: 0.18 linear is 0.4614 encoded (IEC 61966-2-1).
        assert encode(np.full((1, 1, 3), 0.18), "srgb")[0, 0, 0] == pytest.approx(0.46135, abs=1e-4)

    def test_clipped_above_white(self):
        assert encode(np.full((1, 1, 3), 4.0), "bt709").max() == 1.0


@pytest.fixture(scope="module")
def raw_shoot(studio_cache, texture, tmp_path_factory):
    """16 views of the textured scene as DNG files, the first photographed as a 3-shot RAW bracket."""
    scene = textured_scene(texture, views=16, resolution=192)
    radiance = render_scene(scene).radiance
    folder = tmp_path_factory.mktemp("raw")
    files = []
    for view in range(16):
        for factor in (1, 4, 16) if view == 0 else (4,):
            files.append(
                write_dng(
                    folder / f"IMG_{len(files) + 1:04d}.dng",
                    radiance[view] * factor * 0.75,
                    exposure=Fraction(factor, 240),
                )
            )
    out = tmp_path_factory.mktemp("raw-data") / "dataset"
    report = process_data(ProcessDataConfig(images=folder, out=out, camera_model="SIMPLE_PINHOLE", num_threads=2))
    return report, out, folder


class TestProcessRaw:
    def test_bracket_merged_from_linear_data(self, raw_shoot):
        report, out, folder = raw_shoot
        assert len(report.hdr_views) == 1
        merged = report.hdr_views[0]
        assert merged.sources == ["IMG_0001.dng", "IMG_0002.dng", "IMG_0003.dng"]
        assert merged.exposures == pytest.approx([1 / 240, 4 / 240, 16 / 240])
        hdr = read_exr(out / "exr" / f"{merged.name.split('_')[0]}.exr")
        middle, _ = read_raw(folder / "IMG_0002.dng")  # the same demosaicing: only the merge differs
        usable = (middle > 0.05) & (middle < 0.9)
        ratio = hdr[usable] / middle[usable]
        assert np.median(np.abs(ratio / np.median(ratio) - 1)) < 0.005  # linear, up to one scale

    def test_views_are_16_bit_through_the_response(self, raw_shoot):
        report, out, folder = raw_shoot
        single = next(photo for photo in report.views if photo.bracket is None)
        image = read_image(out / "images" / single.name)
        np.testing.assert_allclose(image, encode(read_raw(folder / single.source)[0], "srgb"), atol=1.5 / 65535)
        assert len(np.unique(image)) > 256  # more levels than an 8-bit file holds

    def test_exposures_and_response_recorded(self, raw_shoot):
        report, out, _ = raw_shoot
        assert {photo.exposure_source for photo in report.photos} == {"raw"}
        assert report.response == "srgb (RAW photos)"
        response = json.loads((out / "camera_response.json").read_text())
        assert response["linear_rgb"][-1] == [1.0, 1.0, 1.0]
        assert response["linear_rgb"][128][0] == pytest.approx(decode(np.array(128 / 255), "srgb"), rel=1e-6)
