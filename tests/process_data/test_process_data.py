"""`mono-hdr process-data`: photos -> HDR-GS dataset, checked against known cameras and exposures."""

import json
import math
import os
import shutil
from dataclasses import replace
from fractions import Fraction
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import torch
from helpers import quiet_config, real_photos
from PIL import Image
from process_data_photos import shoot, textured_scene

from mono_hdr_plugin.apps.cli import main as cli_main
from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data
from mono_hdr_plugin.apps.process_data.exposures import (
    assign_exposures,
    exposure_warnings,
    read_exposure_csv,
    relative_exposure,
)
from mono_hdr_plugin.apps.process_data.photos import check_one_camera, find_photos, load_photo
from mono_hdr_plugin.apps.process_data.records import PhotoRecord
from mono_hdr_plugin.apps.process_data.sfm import MapperAttempt, Reconstruction, check_registered
from mono_hdr_plugin.apps.studio.alignment import similarity
from mono_hdr_plugin.apps.studio.shoot import save_jpeg
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.data.photos.exif import PhotoExif, read_exif

ROTATION_LIMIT_DEG = 1.0
POSITION_LIMIT = 0.01
"""Of the scene size (the diagonal of the camera centres' bounding box)."""


def camera_errors(out, cameras) -> tuple[float, float]:
    """(max rotation error in degrees, max position error / scene size) after a similarity alignment."""
    data = load_scene(DataConfig(data=out))
    views = data.train + data.test
    truth = [cameras[int(view.name.split("_")[0])] for view in views]
    estimated = np.array([view.camera.center.double().numpy() for view in views])
    known = np.array([camera.center.double().numpy() for camera in truth])
    scale, rotation, translation = similarity(estimated, known)
    aligned = scale * estimated @ rotation.T + translation
    position = np.linalg.norm(aligned - known, axis=1).max() / np.linalg.norm(known.max(0) - known.min(0))
    angles = []
    for view, camera in zip(views, truth):
        relative = (rotation @ view.camera.c2w[:3, :3].double().numpy()).T @ camera.c2w[:3, :3].double().numpy()
        angles.append(math.degrees(math.acos(np.clip((np.trace(relative) - 1) / 2, -1, 1))))
    return max(angles), position


def plain_photos(folder, count, size=(32, 24), **exif):
    """`count` small random JPEGs: enough for the checks that run before structure from motion."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    return [save_jpeg(folder / f"p{index}.jpg", rng.random((size[1], size[0], 3)), **exif) for index in range(count)]


@pytest.fixture(scope="module")
def processed(small_shoot, tmp_path_factory):
    """The small shoot through process-data with the default (distortion-estimating) camera model."""
    out = tmp_path_factory.mktemp("processed") / "dataset"
    return process_data(ProcessDataConfig(images=small_shoot.folder, out=out, num_threads=2)), out


class TestProcessData:
    def test_every_photo_placed(self, processed, small_shoot):
        report, _ = processed
        assert len(report.registered) == len(small_shoot.names) and report.failed == []
        assert report.num_points > 100 and 0 < report.mean_reprojection_error < 1.0

    def test_cameras_match_the_known_ones(self, processed, small_shoot):
        rotation_error, position_error = camera_errors(processed[1], small_shoot.cameras)
        assert rotation_error < ROTATION_LIMIT_DEG
        assert position_error < POSITION_LIMIT

    def test_undistorted_to_pinhole(self, processed):
        report, out = processed
        assert report.camera_model == "PINHOLE"
        camera = load_scene(DataConfig(data=out)).train[0].camera
        assert (camera.width, camera.height) == (report.width, report.height)

    def test_exposures_read_back_exactly(self, processed, small_shoot):
        _, out = processed
        data = load_scene(DataConfig(data=out))
        recorded = json.loads((out / "process_data.json").read_text())
        by_dataset_name = {photo["name"]: photo["source"] for photo in recorded["photos"]}
        truth = dict(zip(small_shoot.names, small_shoot.exposures))
        for view in data.train + data.test:
            assert view.exposure == truth[by_dataset_name[view.name]]
        assert {photo.exposure_source for photo in processed[0].photos} == {"exif"}

    def test_report_and_files(self, processed):
        report, out = processed
        assert report.exposure_range == (1 / 60, 1 / 15)
        assert report.exposure_stops == pytest.approx(2.0)
        assert report.warnings == []  # three exposures within 2 stops: nothing to warn about
        assert sorted(p.name for p in (out / "images").iterdir()) == sorted(p.name for p in report.registered)
        assert not [p for p in out.parent.iterdir() if p.name.startswith(".")]  # scratch folder removed

    def test_auto_white_balance_reaches_the_trainer(self, processed, tmp_path):
        # The simulated camera writes no WhiteBalance tag, so no white_balance.json: the studio learns no
        # gains. With the file a camera on auto gives, the scene names the photos whose gains to learn.
        _, out = processed
        assert not (out / "white_balance.json").exists()
        assert load_scene(DataConfig(data=out)).metadata["auto_white_balance"] == []
        copy = Path(shutil.copytree(out, tmp_path / "d"))
        names = json.loads((out / "exposures.json").read_text())
        (copy / "white_balance.json").write_text(json.dumps(dict.fromkeys(names, "auto") | {next(iter(names)): None}))
        assert load_scene(DataConfig(data=copy)).metadata["auto_white_balance"] == list(names)[1:]

    def test_pinhole_model_is_kept(self, small_shoot, tmp_path):
        report = process_data(
            ProcessDataConfig(
                images=small_shoot.folder, out=tmp_path / "d", camera_model="SIMPLE_PINHOLE", num_threads=2
            )
        )
        assert report.camera_model == "SIMPLE_PINHOLE" and (report.width, report.height) == (192, 192)
        rotation_error, position_error = camera_errors(tmp_path / "d", small_shoot.cameras)
        assert rotation_error < ROTATION_LIMIT_DEG and position_error < POSITION_LIMIT

    @pytest.mark.slow
    def test_folder_names_that_are_not_utf8(self, small_shoot, tmp_path):
        """Photos and --out under a name POSIX accepts and UTF-8 does not: COLMAP works in a UTF-8 link."""
        odd = tmp_path / os.fsdecode(b"caf\xe9-\xff")
        shutil.copytree(small_shoot.folder, odd / "photos")
        report = process_data(ProcessDataConfig(images=odd / "photos", out=odd / "dataset", num_threads=2))
        assert len(report.registered) == len(small_shoot.names) and report.failed == []
        assert len(load_scene(DataConfig(data=odd / "dataset")).train) > 0
        assert sorted(path.name for path in odd.iterdir()) == ["dataset", "photos"]  # no scratch left

    def test_existing_out_needs_overwrite(self, processed, small_shoot):
        _, out = processed
        before = sorted(p.name for p in out.iterdir())
        with pytest.raises(DatasetError, match="--overwrite"):
            process_data(ProcessDataConfig(images=small_shoot.folder, out=out))
        assert sorted(p.name for p in out.iterdir()) == before

    def test_cli_prints_the_report_and_downscales(self, small_shoot, tmp_path, capsys):
        cli_main(
            [
                "process-data",
                "--images",
                str(small_shoot.folder),
                "--out",
                str(tmp_path / "d"),
                "--camera-model",
                "SIMPLE_PINHOLE",
                "--downscale",
                "2",
                "--num-threads",
                "2",
            ]
        )
        printed = capsys.readouterr().out
        assert f"placed {len(small_shoot.names)} / {len(small_shoot.names)} photos" in printed
        assert "IMG_0001.jpg" in printed and "SIMPLE_PINHOLE 96x96" in printed
        view = load_scene(DataConfig(data=tmp_path / "d")).train[0]
        truth = small_shoot.cameras[0]
        assert tuple(view.image.shape) == (96, 96, 3) and (view.camera.width, view.camera.height) == (96, 96)
        assert view.camera.fx == pytest.approx(truth.fx / 2, rel=0.01)
        assert view.camera.cx == pytest.approx(truth.cx / 2, abs=0.5)


class TestTrainOnResult:
    def test_a_few_steps(self, processed, tmp_path):
        from mono_hdr_plugin.core.registry import BACKBONES
        from mono_hdr_plugin.training.trainer import Trainer

        if "gs" in BACKBONES.available():
            from backbones.gs import DefaultStrategy, GaussianConfig

            name, backbone_config = "gs", GaussianConfig(sh_degree=0, strategy=DefaultStrategy(refine_start=10**9))
        else:
            import register_backbone  # examples/, on sys.path via tests/conftest.py

            name, backbone_config = "voxel-grid", register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=16)
        data = load_scene(DataConfig(data=processed[1], downscale=4))
        config = quiet_config(backbone_config, tmp_path / "run", max_steps=2)
        trainer = Trainer(config, name, data)
        before = [p.detach().clone() for p in trainer.backbone.parameters()]
        records = [trainer.train_step() for _ in range(2)]
        assert all(math.isfinite(record["loss"]) for record in records)
        assert any(not torch.equal(a, b) for a, b in zip(before, trainer.backbone.parameters()))


class TestFindPhotos:
    def test_natural_order_and_suffixes(self, tmp_path):
        for name in ("b10.JPG", "b2.png", "b1.tiff", "notes.txt", ".hidden.jpg"):
            (tmp_path / name).write_bytes(b"")
        photos, ignored = find_photos(tmp_path)
        assert [p.name for p in photos] == ["b1.tiff", "b2.png", "b10.JPG"] and ignored == []

    def test_raw_twin_is_preferred(self, tmp_path):
        for name in ("a.CR2", "a.JPG", "b.jpg", "c.nef"):
            (tmp_path / name).write_bytes(b"")
        photos, ignored = find_photos(tmp_path)
        assert [p.name for p in photos] == ["a.CR2", "b.jpg", "c.nef"] and ignored == ["a.JPG"]

    def test_empty_folder(self, tmp_path):
        with pytest.raises(DatasetError, match="no photos found"):
            find_photos(tmp_path)

    def test_missing_folder(self, tmp_path):
        with pytest.raises(DatasetError, match="--images"):
            find_photos(tmp_path / "nope")

    def test_fewer_than_three(self, tmp_path):
        plain_photos(tmp_path, 2)
        with pytest.raises(DatasetError, match="only 2 photo"):
            process_data(ProcessDataConfig(images=tmp_path, out=tmp_path / "out"))


class TestCheckConfig:
    @pytest.mark.parametrize(
        "change,message",
        [
            ({"downscale": 3}, "--downscale"),
            ({"min_registered": 0.0}, "--min-registered"),
            ({"exposure": -1.0}, "--exposure"),
            ({"out": None}, "--out must differ"),
        ],
    )
    def test_bad_flags(self, tmp_path, change, message):
        plain_photos(tmp_path, 3)
        config = replace(ProcessDataConfig(images=tmp_path, out=tmp_path / "out"), **change)
        if config.out is None:
            config.out = tmp_path
            config.overwrite = True
        with pytest.raises(FlagError, match=message):
            process_data(config)

    def test_out_is_a_file(self, tmp_path):
        plain_photos(tmp_path / "photos", 3)
        (tmp_path / "out").write_text("")
        with pytest.raises(DatasetError, match="is a file"):
            process_data(ProcessDataConfig(images=tmp_path / "photos", out=tmp_path / "out", overwrite=True))


class TestLoadPhoto:
    def test_exif_orientation_is_applied(self, tmp_path):
        pixels = np.zeros((2, 4, 3))
        pixels[0, 0] = 1.0  # top-left marker
        # Orientation 6: the camera was turned 90 degrees clockwise; viewers rotate the image back.
        upright, _ = load_photo(save_jpeg(tmp_path / "r.jpg", pixels, orientation=6))
        assert upright.shape == (4, 2, 3)
        assert upright[0, -1].mean() > 0.5 and upright[0, 0].mean() < 0.5

    def test_png_and_tiff(self, tmp_path):
        image = Image.fromarray(np.full((5, 7, 3), 128, np.uint8))
        for suffix in ("png", "tif"):
            image.save(tmp_path / f"a.{suffix}")
            pixels, exif = load_photo(tmp_path / f"a.{suffix}")
            assert pixels.shape == (5, 7, 3) and pixels.max() == pytest.approx(128 / 255)
            assert exif.exposure_time is None

    def test_unreadable_photo_names_the_file(self, tmp_path):
        photos = plain_photos(tmp_path, 4)
        photos[1].write_bytes(photos[1].read_bytes()[:200])
        with pytest.raises(DatasetError, match="p1.jpg.*cannot read the photo"):
            process_data(ProcessDataConfig(images=tmp_path, out=tmp_path / "out"))
        assert not (tmp_path / "out").exists()


class TestReadExif:
    def test_exposure_aperture_iso_camera(self, tmp_path):
        path = save_jpeg(
            tmp_path / "a.jpg",
            np.zeros((4, 4, 3)),
            exposure=Fraction(1, 60),
            iso=400,
            f_number=Fraction(28, 10),
            focal_35mm=26,
            model="Pixel 8",
        )
        with Image.open(path) as image:
            exif = read_exif(image)
        assert exif == PhotoExif(
            exposure_time=1 / 60, f_number=2.8, iso=400.0, focal_35mm=26.0, camera="Mono-HDR Pixel 8"
        )

    def test_gps_south_and_west_below_sea_level(self, tmp_path):
        path = save_jpeg(tmp_path / "a.jpg", np.zeros((4, 4, 3)), gps=(-33.85675, -151.21525, -12.5))
        with Image.open(path) as image:
            assert read_exif(image).gps == pytest.approx((-33.85675, -151.21525, -12.5), abs=1e-6)

    def test_gps_as_a_phone_writes_it(self, tmp_path):
        # Lund, as the opensfm_lund photos carry it: 55 deg 41' 53.4" N, 13 deg 11' 43.4" E, 37 m
        exif = Image.Exif()
        exif.get_ifd(0x8825).update({1: "N", 2: (55.0, 41.0, 53.4), 3: "E", 4: (13.0, 11.0, 43.4), 6: 37.0})
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "a.jpg", exif=exif)
        with Image.open(tmp_path / "a.jpg") as image:
            assert read_exif(image).gps == pytest.approx((55 + 41 / 60 + 53.4 / 3600, 13 + 11 / 60 + 43.4 / 3600, 37))

    def test_no_exif(self, tmp_path):
        Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "a.jpg")
        with Image.open(tmp_path / "a.jpg") as image:
            assert read_exif(image) == PhotoExif()

    def test_white_balance_mode(self, tmp_path):
        for value, mode in ((0, "auto"), (1, "manual"), (None, None)):
            path = save_jpeg(tmp_path / f"{value}.jpg", np.zeros((4, 4, 3)), white_balance=value)
            with Image.open(path) as image:
                assert read_exif(image).white_balance == mode

    def test_the_lund_photos_say_auto_white_balance(self):
        # A phone's photos: EXIF WhiteBalance 0 (auto), and no gains anywhere a reader can decode.
        with Image.open(real_photos("opensfm_lund") / "images" / "01.jpg") as image:
            assert read_exif(image).white_balance == "auto"

    def test_zero_exposure_counts_as_missing(self, tmp_path):
        path = save_jpeg(tmp_path / "a.jpg", np.zeros((4, 4, 3)), exposure=Fraction(0, 1))
        with Image.open(path) as image:
            assert read_exif(image).exposure_time is None


class TestRelativeExposure:
    def test_known_value(self):
        # 1/100 s at ISO 400, f/4 against ISO 100, f/2.8: 4x the gain, (2.8/4)^2 = 0.49 of the light.
        assert relative_exposure(0.01, 400, 4.0, 100, 2.8) == pytest.approx(0.01 * 4 * 0.49)

    def test_reference_settings_keep_the_time(self):
        assert relative_exposure(1 / 60, 200, 2.8, 200, 2.8) == 1 / 60

    def test_equivalent_exposures_agree(self):
        # One stop less time, one stop more ISO, the same light: the same relative exposure.
        assert relative_exposure(1 / 30, 100, 4.0, 100, 2.8) == pytest.approx(
            relative_exposure(1 / 60, 200, 4.0, 100, 2.8)
        )
        assert relative_exposure(1 / 30, 100, 4.0, 100, 2.8) == pytest.approx(
            relative_exposure(1 / 60, 100, 4.0 / math.sqrt(2), 100, 2.8)
        )


class TestAssignExposures:
    def test_sources_in_order_exif_csv_flag(self):
        exifs = [PhotoExif(exposure_time=0.5), PhotoExif(), PhotoExif()]
        exposures, _ = assign_exposures(["a", "b", "c"], exifs, {"b": 0.25}, 0.125)
        assert exposures == [(0.5, "exif"), (0.25, "csv"), (0.125, "flag")]

    def test_no_exposure_anywhere_is_unknown(self):
        exposures, _ = assign_exposures(["a", "b"], [PhotoExif(), PhotoExif()], {}, None)
        assert exposures == [(None, "unknown"), (None, "unknown")]

    def test_raw_metadata_is_named(self):
        exposures, _ = assign_exposures(["a.dng"], [PhotoExif(exposure_time=0.5)], {}, None, raw=[True])
        assert exposures == [(0.5, "raw")]

    def test_missing_exposure_says_what_to_pass(self):
        with pytest.raises(DatasetError, match=r"b, c.*--exposure SECONDS.*--exposure-csv"):
            assign_exposures(["a", "b", "c"], [PhotoExif(exposure_time=0.5), PhotoExif(), PhotoExif()], {}, None)

    def test_csv_names_unknown_photo(self, tmp_path):
        with pytest.raises(DatasetError, match="not in --images: typo.jpg"):
            assign_exposures(["a"], [PhotoExif()], {"typo.jpg": 1.0}, None, tmp_path / "e.csv")

    def test_fixed_iso_and_aperture_keep_exact_times(self):
        exifs = [PhotoExif(exposure_time=t, iso=100, f_number=2.8) for t in (1 / 60, 1 / 250)]
        exposures, reference = assign_exposures(["a", "b"], exifs, {}, None)
        assert [t for t, _ in exposures] == [1 / 60, 1 / 250]
        assert reference == {"iso": None, "f_number": None}

    def test_varying_iso_and_aperture_are_folded(self):
        exifs = [
            PhotoExif(exposure_time=0.01, iso=100, f_number=2.8),
            PhotoExif(exposure_time=0.01, iso=100, f_number=2.8),
            PhotoExif(exposure_time=0.01, iso=400, f_number=4.0),
        ]
        exposures, reference = assign_exposures(["a", "b", "c"], exifs, {}, None)
        assert reference == {"iso": 100, "f_number": 2.8}  # the most common settings
        assert exposures[0] == (0.01, "exif")
        assert exposures[2][0] == pytest.approx(relative_exposure(0.01, 400, 4.0, 100, 2.8))


class TestReadExposureCsv:
    def test_header_and_rows(self, tmp_path):
        path = tmp_path / "e.csv"
        path.write_text("name,seconds\nIMG_1.jpg, 0.5\n\nIMG_2.jpg,1/1\n".replace("1/1", "1"))
        assert read_exposure_csv(path) == {"IMG_1.jpg": 0.5, "IMG_2.jpg": 1.0}

    def test_bad_value_names_the_line(self, tmp_path):
        path = tmp_path / "e.csv"
        path.write_text("a.jpg,0.5\nb.jpg,-1\n")
        with pytest.raises(DatasetError, match=r"e.csv:2 \(b.jpg\).*positive"):
            read_exposure_csv(path)

    def test_duplicate_row(self, tmp_path):
        path = tmp_path / "e.csv"
        path.write_text("a.jpg,0.5\na.jpg,0.25\n")
        with pytest.raises(DatasetError, match="listed twice"):
            read_exposure_csv(path)

    def test_csv_used_end_to_end(self, tmp_path):
        plain_photos(tmp_path / "photos", 3)
        (tmp_path / "e.csv").write_text("p0.jpg,0.5\n")
        with pytest.raises(DatasetError, match=r"2 photo\(s\) have no exposure time.*p1.jpg, p2.jpg"):
            process_data(
                ProcessDataConfig(images=tmp_path / "photos", out=tmp_path / "out", exposure_csv=tmp_path / "e.csv")
            )


class TestCheckOneCamera:
    def test_mixed_sizes(self, tmp_path):
        with pytest.raises(DatasetError, match=r"different sizes.*2 at 40x30.*1 at 30x36 \(e.g. c.jpg\)"):
            check_one_camera(["a.jpg", "b.jpg", "c.jpg"], [(40, 30), (40, 30), (30, 36)], [PhotoExif()] * 3, tmp_path)

    def test_portrait_and_landscape_of_one_size_pass(self, tmp_path):
        check_one_camera(["a.jpg", "b.jpg", "c.jpg"], [(40, 30), (40, 30), (30, 40)], [PhotoExif()] * 3, tmp_path)

    def test_mixed_camera_models(self, tmp_path):
        plain_photos(tmp_path / "photos", 2, exposure=Fraction(1, 50), model="Canon EOS R5")
        save_jpeg(tmp_path / "photos" / "z.jpg", np.zeros((24, 32, 3)), exposure=Fraction(1, 50), model="Pixel 8")
        with pytest.raises(DatasetError, match="several cameras.*'Mono-HDR Pixel 8'.*own folder"):
            process_data(ProcessDataConfig(images=tmp_path / "photos", out=tmp_path / "out"))

    def test_one_camera_passes(self, tmp_path):
        check_one_camera(["a", "b"], [(4, 3), (4, 3)], [PhotoExif(camera="X"), PhotoExif()], tmp_path)


class TestTooFewRegistered:
    def test_featureless_photos(self, tmp_path):
        for index in range(4):
            save_jpeg(tmp_path / f"grey{index}.jpg", np.full((64, 64, 3), 0.5), exposure=Fraction(1, 50))
        with pytest.raises(DatasetError, match="placed no photos.*overlap"):
            process_data(ProcessDataConfig(images=tmp_path, out=tmp_path / "out", num_threads=2))
        assert not (tmp_path / "out").exists()

    def test_unplaceable_photos_are_listed(self, small_shoot, tmp_path):
        # Three unrelated noise photos join the shoot: they cannot be placed, and are reported.
        photos = tmp_path / "photos"
        photos.mkdir()
        for name in small_shoot.names:
            (photos / name).write_bytes((small_shoot.folder / name).read_bytes())
        rng = np.random.default_rng(1)
        for index in range(3):
            save_jpeg(
                photos / f"ZZ_noise{index}.jpg",
                rng.random((192, 192, 3)),
                exposure=Fraction(1, 60),
                iso=100,
                f_number=Fraction(28, 10),
                focal_35mm=35,
            )
        report = process_data(
            ProcessDataConfig(images=photos, out=tmp_path / "out", camera_model="SIMPLE_PINHOLE", num_threads=2)
        )
        assert report.failed == ["ZZ_noise0.jpg", "ZZ_noise1.jpg", "ZZ_noise2.jpg"]
        assert any("could not be placed" in note and "ZZ_noise1.jpg" in note for note in report.warnings)
        assert not (tmp_path / "out" / "images" / "016_0.png").exists()

    def test_below_min_registered_is_an_error(self, tmp_path):
        photos = [
            PhotoRecord(
                source=f"{i}.jpg", name=f"{i:03d}_0.png", exposure=0.01, exposure_source="exif", registered=i < 5
            )
            for i in range(10)
        ]
        config = ProcessDataConfig(images=tmp_path, out=tmp_path / "out", min_registered=0.6)
        attempts = [MapperAttempt("incremental", 2, 0.5, 1.0), MapperAttempt("global", 5, 0.7, 1.0)]
        split = Reconstruction(model=None, matcher="exhaustive", groups=2, mapper="global", attempts=attempts)
        with pytest.raises(
            DatasetError, match=r"placed only 5 of 10 photos \(need 6.*2 separate groups.*5.jpg, 6.jpg"
        ) as error:
            check_registered(config, photos, split)
        # the advice names what was tried and only what was not: exhaustive matching and the default
        # lens model ran already
        assert "exhaustive matching; incremental placed 2, global placed 5" in str(error.value)
        assert "--matcher" not in str(error.value) and "--camera-model" not in str(error.value)
        one = Reconstruction(model=None, matcher="sequential", groups=1, mapper="incremental", attempts=attempts[:1])
        with pytest.raises(DatasetError, match=r"try --matcher exhaustive and --mapper auto"):
            check_registered(replace(config, mapper="incremental", matcher="sequential"), photos, one)
        assert check_registered(replace(config, min_registered=0.5), photos, one) != []


class TestExposureWarnings:
    @staticmethod
    def photos(*exposures):
        return [
            PhotoRecord(
                source=f"{i}.jpg", name=f"{i:03d}_0.png", exposure=e, exposure_source="exif", registered=True, view=True
            )
            for i, e in enumerate(exposures)
        ]

    def test_single_exposure(self):
        notes = exposure_warnings(self.photos(0.01, 0.01, 0.01), {"iso": None, "f_number": None})
        assert len(notes) == 1 and "same exposure" in notes[0]

    def test_wide_range(self):
        notes = exposure_warnings(self.photos(1 / 4000, 1 / 2), {"iso": None, "f_number": None})
        assert len(notes) == 1 and "11.0 stops" in notes[0]

    def test_photo_missing_a_varying_setting_is_named(self):
        photos = self.photos(0.01, 0.02)
        photos[0].iso = 100.0
        notes = exposure_warnings(photos, {"iso": 100.0, "f_number": None})
        assert len(notes) == 1 and "1.jpg" in notes[0] and "reference value was assumed" in notes[0]

    def test_unknown_exposures(self):
        photos = self.photos(1.0, 1.0)
        for photo in photos:
            photo.exposure, photo.exposure_source = None, "unknown"
        notes = exposure_warnings(photos, {"iso": None, "f_number": None})
        assert len(notes) == 1 and "treating every photo as one unknown exposure" in notes[0]

    def test_moderate_range_is_quiet(self):
        assert exposure_warnings(self.photos(1 / 60, 1 / 15), {"iso": None, "f_number": None}) == []


class TestMixedOrientations:
    def test_portrait_and_landscape_photos_of_one_lens(self, studio_cache, texture, tmp_path):
        # 12 landscape photos and 6 portrait ones between them, the same lens turned: one focal in pixels
        landscape_fov = 55.0
        portrait_fov = math.degrees(2 * math.atan(144 / 192 * math.tan(math.radians(landscape_fov / 2))))
        landscape = textured_scene(texture, views=12, resolution=(192, 144), fov_deg=landscape_fov)
        portrait = textured_scene(texture, 6, (144, 192), azimuth_deg=(-140.0, -40.0), fov_deg=portrait_fov)
        folder = tmp_path / "photos"
        first = shoot(landscape, folder, [Fraction(1, 60)])
        second = shoot(portrait, folder, [Fraction(1, 60)], first_number=13)
        report = process_data(ProcessDataConfig(images=folder, out=tmp_path / "d", num_threads=2))
        assert report.failed == [] and len(report.registered) == 18
        # every view cut to the centred square both orientations share
        side = report.width  # COLMAP's undistorter may trim a pixel
        assert report.height == side and 142 <= side <= 144
        model = pycolmap.Reconstruction(tmp_path / "d" / "sparse" / "0")
        assert len(model.cameras) == 2 and {(c.width, c.height) for c in model.cameras.values()} == {(side, side)}
        # each principal point moved with its cut (24 px from the left of a landscape photo, from the
        # top of a portrait one): both near the middle of the square again
        principal = sorted((round(c.principal_point_x), round(c.principal_point_y)) for c in model.cameras.values())
        assert all(abs(x - side / 2) <= 3 and abs(y - side / 2) <= 3 for x, y in principal), principal
        rotation_error, position_error = camera_errors(tmp_path / "d", first.cameras + second.cameras)
        assert rotation_error < ROTATION_LIMIT_DEG and position_error < POSITION_LIMIT

    def test_other_sizes_are_still_refused(self, tmp_path):
        plain_photos(tmp_path / "p", 2, size=(32, 24))
        plain_photos(tmp_path / "q", 1, size=(30, 24))
        (tmp_path / "q" / "p0.jpg").rename(tmp_path / "p" / "z.jpg")
        with pytest.raises(DatasetError, match=r"photos of different sizes.*2 at 32x24.*1 at 30x24"):
            process_data(ProcessDataConfig(images=tmp_path / "p", out=tmp_path / "d"))


@pytest.mark.slow
class TestLargerShoot:
    def test_24_views_at_256_px(self, studio_cache, texture, tmp_path):
        scene = textured_scene(texture, views=24, resolution=256)
        photos = shoot(scene, tmp_path / "photos", [Fraction(1, 125)])
        report = process_data(
            ProcessDataConfig(images=photos.folder, out=tmp_path / "d", matcher="sequential", num_threads=2)
        )
        assert report.failed == []
        assert any("same exposure" in note for note in report.warnings)
        rotation_error, position_error = camera_errors(tmp_path / "d", photos.cameras)
        assert rotation_error < ROTATION_LIMIT_DEG / 2 and position_error < POSITION_LIMIT / 2
