"""Image IO: PNG 8/16 bit, JPEG, EXR; corrupt and odd files give errors naming the file."""

import os

import numpy as np
import pytest
from PIL import Image

from mono_hdr_plugin.data.errors import DatasetError, MissingFileError
from mono_hdr_plugin.data.io import read_exr, read_image, write_exr, write_png


@pytest.fixture
def image():
    return np.random.default_rng(0).random((6, 7, 3), dtype=np.float32)


def truncate(path, keep_fraction=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep_fraction)])


class TestReadWritePng:
    @pytest.mark.parametrize("bits", [8, 16])
    def test_round_trip_within_one_level(self, tmp_path, image, bits):
        path = tmp_path / "a.png"
        write_png(path, image, bits=bits)
        back = read_image(path)
        assert back.dtype == np.float32 and back.shape == (6, 7, 3)
        assert np.abs(back - image).max() <= 0.5 / (2**bits - 1) + 1e-6

    def test_16_bit_keeps_levels_that_8_bit_cannot_hold(self, tmp_path):
        ramp = (np.arange(30000, 30011) / 65535).astype(np.float32)
        image = np.broadcast_to(ramp[None, :, None], (2, 11, 3)).copy()
        write_png(tmp_path / "r.png", image, bits=16)
        assert len(np.unique(read_image(tmp_path / "r.png"))) == 11

    def test_rgba_drops_alpha(self, tmp_path):
        rgba = np.zeros((3, 4, 4), np.uint8)
        rgba[..., 0], rgba[..., 3] = 200, 10
        Image.fromarray(rgba, mode="RGBA").save(tmp_path / "a.png")
        back = read_image(tmp_path / "a.png")
        assert back.shape == (3, 4, 3)
        assert np.allclose(back[..., 0], 200 / 255) and np.allclose(back[..., 1:], 0)

    def test_jpeg(self, tmp_path, image):
        smooth = np.broadcast_to(np.linspace(0, 1, 16)[None, :, None], (8, 16, 3))
        Image.fromarray((smooth * 255).astype(np.uint8)).save(tmp_path / "a.jpg", quality=100)
        assert np.abs(read_image(tmp_path / "a.jpg") - smooth).max() < 0.02

    def test_clips_out_of_range(self, tmp_path):
        write_png(tmp_path / "c.png", np.full((2, 2, 3), 3.0, np.float32))
        assert np.all(read_image(tmp_path / "c.png") == 1.0)

    def test_atomic_no_temporary_left(self, tmp_path, image):
        write_png(tmp_path / "a.png", image)
        assert os.listdir(tmp_path) == ["a.png"]

    def test_bad_bits(self, tmp_path, image):
        with pytest.raises(ValueError, match="bits"):
            write_png(tmp_path / "a.png", image, bits=12)


class TestReadImageErrors:
    def test_missing_file_names_it(self, tmp_path):
        with pytest.raises(MissingFileError, match="nope.png"):
            read_image(tmp_path / "nope.png")

    @pytest.mark.parametrize("bits", [8, 16])
    def test_truncated_png(self, tmp_path, image, bits):
        path = tmp_path / "t.png"
        write_png(path, np.random.default_rng(1).random((64, 64, 3)), bits=bits)
        truncate(path)
        with pytest.raises(DatasetError, match="t.png.*truncated or corrupt"):
            read_image(path)

    def test_truncated_jpeg(self, tmp_path):
        path = tmp_path / "t.jpg"
        Image.fromarray((np.random.default_rng(2).random((64, 64, 3)) * 255).astype(np.uint8)).save(path)
        truncate(path)
        with pytest.raises(DatasetError, match="t.jpg.*truncated or corrupt"):
            read_image(path)

    def test_not_an_image(self, tmp_path):
        (tmp_path / "x.png").write_text("hello")
        with pytest.raises(DatasetError, match="x.png"):
            read_image(tmp_path / "x.png")

    def test_grayscale_is_wrong_channel_count(self, tmp_path):
        Image.fromarray(np.zeros((3, 3), np.uint8), mode="L").save(tmp_path / "g.png")
        with pytest.raises(DatasetError, match="g.png.*1 channel.*convert it to RGB"):
            read_image(tmp_path / "g.png")


class TestReadWriteExr:
    def test_float32_round_trip_is_exact(self, tmp_path, image):
        hdr = image * 1e5
        write_exr(tmp_path / "a.exr", hdr)
        assert np.array_equal(read_exr(tmp_path / "a.exr"), hdr)

    def test_non_contiguous_input_writes_right_pixels(self, tmp_path, image):
        view = image[:, ::-1]
        write_exr(tmp_path / "a.exr", view)
        assert np.array_equal(read_exr(tmp_path / "a.exr"), view)

    def test_float64_input_accepted(self, tmp_path, image):
        write_exr(tmp_path / "a.exr", image.astype(np.float64))
        assert np.allclose(read_exr(tmp_path / "a.exr"), image)

    def test_half(self, tmp_path, image):
        write_exr(tmp_path / "h.exr", image, half=True)
        assert np.allclose(read_exr(tmp_path / "h.exr"), image, rtol=1e-3, atol=1e-4)

    def test_half_overflow_is_an_error(self, tmp_path, image):
        with pytest.raises(DatasetError, match="h.exr.*65504.*half=False"):
            write_exr(tmp_path / "h.exr", image * 1e5, half=True)
        assert not (tmp_path / "h.exr").exists()

    def test_writing_nan_is_an_error(self, tmp_path, image):
        image[0, 0, 0] = np.nan
        with pytest.raises(DatasetError, match="NaN"):
            write_exr(tmp_path / "n.exr", image)


class TestReadExrErrors:
    def _write_raw(self, path, channels):
        import OpenEXR

        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        OpenEXR.File(header, channels).write(str(path))

    @pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
    def test_nan_inf(self, tmp_path, image, bad):
        image[2, 3, 1] = bad
        self._write_raw(tmp_path / "bad.exr", {"RGB": image})
        with pytest.raises(DatasetError, match="bad.exr: 1 pixel.*NaN or Inf"):
            read_exr(tmp_path / "bad.exr")

    def test_missing(self, tmp_path):
        with pytest.raises(MissingFileError, match="gone.exr"):
            read_exr(tmp_path / "gone.exr")

    def test_truncated(self, tmp_path, image):
        write_exr(tmp_path / "t.exr", image)
        truncate(tmp_path / "t.exr", 0.3)
        with pytest.raises(DatasetError, match="t.exr.*truncated or corrupt"):
            read_exr(tmp_path / "t.exr")

    def test_single_channel_is_wrong_channel_count(self, tmp_path, image):
        self._write_raw(tmp_path / "y.exr", {"Y": np.ascontiguousarray(image[..., 0])})
        with pytest.raises(DatasetError, match="y.exr.*channels.*R, G, B"):
            read_exr(tmp_path / "y.exr")

    def test_rgba_drops_alpha(self, tmp_path):
        rgba = np.random.default_rng(3).random((4, 5, 4)).astype(np.float32)
        self._write_raw(tmp_path / "a.exr", {"RGBA": rgba})
        assert np.array_equal(read_exr(tmp_path / "a.exr"), rgba[..., :3])
