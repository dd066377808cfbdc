"""Paths and sizes (issue 48): a dataset or a run under a folder whose name is not UTF-8 (POSIX file
systems take any bytes) works as any other, and a --downscale beyond an image names the flag, the
image and the largest factor that works. docs/robustness.md lists both."""

import json
import math
import os
import shutil

import numpy as np
import pytest
import torch
from cli_driver import run_cli, train_args, write_driver
from hard_scenes import write_disk_scene

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_exr, read_image, write_exr, write_png
from mono_hdr_plugin.data.layouts import writable_layouts
from mono_hdr_plugin.data.loading import load_scene

NOT_UTF8 = os.fsdecode(b"caf\xe9-\xff")  # a Latin-1 e-acute and a byte that no UTF-8 text holds
ESCAPED = r"caf\udce9-\udcff"  # how Python's backslashreplace prints that name


@pytest.fixture
def odd_folder(tmp_path):
    folder = tmp_path / NOT_UTF8
    try:
        folder.mkdir()
    except (OSError, UnicodeEncodeError):
        pytest.skip("this file system refuses names that are not UTF-8 (macOS's APFS does)")
    return folder


class TestFolderNamesThatAreNotUtf8:
    @pytest.mark.parametrize("layout", writable_layouts())
    def test_every_layout_writes_and_reads_the_same_scene(self, tmp_path, odd_folder, layout):
        write_disk_scene(tmp_path / "plain", layout=layout)
        write_disk_scene(odd_folder / "scene", layout=layout)
        plain, odd = load_scene(DataConfig(data=tmp_path / "plain")), load_scene(DataConfig(data=odd_folder / "scene"))
        assert len(odd.train) == len(plain.train) > 0 and len(odd.test) == len(plain.test)
        for expected, view in zip(plain.train + plain.test, odd.train + odd.test, strict=True):
            assert torch.equal(view.image, expected.image)
            assert (view.hdr is None) == (expected.hdr is None)
            assert view.hdr is None or torch.equal(view.hdr, expected.hdr)
            torch.testing.assert_close(view.camera.c2w, expected.camera.c2w)

    def test_16_bit_png_and_exr_round_trip(self, odd_folder):
        image = np.random.default_rng(0).random((5, 6, 3), dtype=np.float32)
        write_png(odd_folder / "a.png", image, bits=16)
        write_exr(odd_folder / "a.exr", image * 40)
        assert np.abs(read_image(odd_folder / "a.png") - image).max() <= 0.5 / 65535 + 1e-7
        np.testing.assert_array_equal(read_exr(odd_folder / "a.exr"), image * 40)

    def test_training_runs_and_writes_there(self, tmp_path, odd_folder, disk_scene):
        shutil.copytree(disk_scene, odd_folder / "scene")
        result = run_cli(write_driver(tmp_path), train_args(odd_folder / "scene", odd_folder / "run", 1))
        assert result.returncode == 0, result.stderr
        assert (odd_folder / "run" / "metrics.json").is_file()

    def test_an_error_prints_the_name_as_one_line(self, tmp_path, odd_folder):
        """On a terminal whose Python encodes strictly (an en_US.UTF-8 locale, not C.UTF-8's UTF-8 mode)."""
        args = train_args(odd_folder / "missing", tmp_path / "run", 1)
        result = run_cli(write_driver(tmp_path), args, PYTHONIOENCODING="utf-8:strict")
        assert result.returncode == 2
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and ESCAPED in lines[0], result.stderr
        assert not (tmp_path / "run").exists()


@pytest.fixture(scope="module")
def scene_24px(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene-24px") / "scene"
    write_disk_scene(folder, size=24)
    return folder


class TestDownscaleBeyondTheImage:
    """Training and evaluation need SSIM's 11 pixels a side: a 24 px scene allows --downscale 2."""

    def test_a_data_folder_names_the_flag_the_image_and_the_largest_factor(self, tmp_path, scene_24px):
        out = tmp_path / "run"
        message = (
            r"--downscale 3 leaves .* of scene .* \(24x24\) under 11 pixels a side; the largest factor that works is 2"
        )
        with pytest.raises(FlagError, match=message):
            main(train_args(scene_24px, out, 1, "--downscale", "3"))
        assert not out.exists()

    def test_the_largest_factor_named_trains(self, tmp_path, scene_24px):
        main(train_args(scene_24px, tmp_path / "run", 1, "--downscale", "2"))
        metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
        assert math.isfinite(metrics["ldr_psnr"])

    def test_a_built_in_scene_alike(self, tmp_path):
        """The tests' built-in scenes are 24 px (conftest)."""
        out = tmp_path / "run"
        with pytest.raises(
            FlagError, match=r"--downscale 200 leaves .* \(24x24\) .* the largest factor that works is 2"
        ):
            main(
                ["train", "voxel-grid", "--scene", "demo", "--downscale", "200", "--out", str(out), "--max-steps", "1"]
            )
        assert not out.exists()

    def test_images_too_small_at_any_factor_are_named(self, tmp_path):
        """A 10 px scene cannot train, and no flag can help."""
        small = tmp_path / "scene"
        write_disk_scene(small, size=10)
        with pytest.raises(DatasetError, match=r"\(10x10\) is under the 11 pixels a side this command needs"):
            main(train_args(small, tmp_path / "run", 1))

    def test_the_command_line_says_it_in_one_line_and_exits_2(self, tmp_path, scene_24px):
        result = run_cli(write_driver(tmp_path), train_args(scene_24px, tmp_path / "run", 1, "--downscale", "200"))
        assert result.returncode == 2
        assert result.stderr.strip().startswith("error: --downscale 200 leaves"), result.stderr
        assert len(result.stderr.strip().splitlines()) == 1 and "must be positive" not in result.stderr
