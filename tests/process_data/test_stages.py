"""Each stage of process-data alone, on small synthetic inputs (no structure from motion): the flag
checks, reading photos, exposures, the registered photos, bracket plans and merges, the layout files
and the report. The end-to-end runs are in test_process_data.py, test_shoot.py and test_video.py."""

import io
import json
import math
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest
from rich.console import Console

from mono_hdr_plugin.apps.cli import main as cli_main
from mono_hdr_plugin.apps.process_data.brackets import (
    bracket_response,
    mark_views,
    merge_plan,
    plan_brackets,
    response_curve,
)
from mono_hdr_plugin.apps.process_data.config import ProcessDataConfig, check_config
from mono_hdr_plugin.apps.process_data.exposures import exposure_warnings, photo_records
from mono_hdr_plugin.apps.process_data.layout import choose_test_views, install, write_metadata
from mono_hdr_plugin.apps.process_data.photos import StagedPhoto, find_inputs, stage_photos
from mono_hdr_plugin.apps.process_data.records import HdrView, PhotoRecord
from mono_hdr_plugin.apps.process_data.report import ProcessReport, print_report
from mono_hdr_plugin.apps.process_data.sfm import (
    MAPPERS,
    MapperAttempt,
    Reconstruction,
    best_attempt,
    check_registered,
    choose_mappers,
    choose_matcher,
    gps_metres,
    gps_rms_metres,
    mark_registered,
)
from mono_hdr_plugin.apps.studio.shoot import save_jpeg
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import write_png
from mono_hdr_plugin.data.photos.brackets import BracketTolerances
from mono_hdr_plugin.data.photos.exif import PhotoExif
from mono_hdr_plugin.data.photos.raw import decode, encode


def jpegs(folder: Path, count: int, size=(32, 24)) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    return [save_jpeg(folder / f"p{index}.jpg", rng.random((size[1], size[0], 3))) for index in range(count)]


def record(index: int, exposure: float | None = 0.01, **fields) -> PhotoRecord:
    return PhotoRecord(
        source=f"p{index}.jpg",
        name=f"{index:03d}_0.png",
        exposure=exposure,
        exposure_source="exif" if exposure else "unknown",
        **fields,
    )


class TestConfigStage:
    @pytest.mark.parametrize(
        "change,message",
        [
            ({"test_every": 1}, r"--test-every must be an integer >= 2, got 1"),
            ({"fps": 0.0}, r"--fps must be a positive number, got 0.0"),
            ({"min_sharpness": 1.0}, r"--min-sharpness must be a number in \[0, 1\), got 1.0"),
            ({"min_registered": 0.0}, r"--min-registered must be a number in \(0, 1\], got 0.0"),
            ({"exposure": -1.0}, r"--exposure must be a positive number, got -1.0"),
            ({"bracket": BracketTolerances(max_gap=math.nan)}, r"--bracket.max-gap must be a finite number, got nan"),
            ({"downscale": 3}, r"--downscale must be 1, 2 or 4, got 3"),
            (
                {"video": Path("walk.mp4")},
                r"pass either --images FOLDER \(photos\) or --video FILE, not both or neither",
            ),
        ],
    )
    def test_flag_checks_name_the_flag(self, tmp_path, change, message):
        config = replace(ProcessDataConfig(images=tmp_path, out=tmp_path / "out"), **change)
        with pytest.raises(FlagError, match=f"^{message}$"):
            check_config(config)

    def test_out_must_differ_from_images(self, tmp_path):
        jpegs(tmp_path, 3)
        with pytest.raises(FlagError, match="^--out must differ from --images"):
            check_config(ProcessDataConfig(images=tmp_path, out=tmp_path, overwrite=True))

    def test_defaults_pass(self, tmp_path):
        check_config(ProcessDataConfig(images=tmp_path, out=tmp_path / "out"))

    def test_the_command_line_refuses_before_any_work(self, tmp_path):
        jpegs(tmp_path / "photos", 3)
        with pytest.raises(FlagError, match="^--test-every must be an integer >= 2, got 0$"):
            cli_main(
                [
                    "process-data",
                    "--images",
                    str(tmp_path / "photos"),
                    "--out",
                    str(tmp_path / "out"),
                    "--test-every",
                    "0",
                ]
            )
        assert sorted(path.name for path in tmp_path.iterdir()) == ["photos"]


class TestPhotosStage:
    def test_folder_photos_are_staged_for_sfm(self, tmp_path):
        jpegs(tmp_path / "photos", 3)
        (tmp_path / "work" / "input").mkdir(parents=True)
        config = ProcessDataConfig(images=tmp_path / "photos", out=tmp_path / "out")
        sources, ignored, video = find_inputs(config, tmp_path / "work" / "frames", Console(quiet=True))
        assert [path.name for path in sources] == ["p0.jpg", "p1.jpg", "p2.jpg"] and ignored == [] and video is None
        staged, sizes = stage_photos(sources, tmp_path / "work", "srgb", Console(quiet=True))
        assert sizes == [(32, 24)] * 3
        assert [stage.name for stage in staged] == ["000_0.png", "001_0.png", "002_0.png"]
        assert all((tmp_path / "work" / "input" / stage.name).is_file() for stage in staged)
        assert all(0.4 < stage.brightness < 0.6 and not stage.raw for stage in staged)

    def test_one_unreadable_photo_lists_it(self, tmp_path):
        photos = jpegs(tmp_path / "photos", 3)
        photos[2].write_bytes(b"not a photo")
        (tmp_path / "work" / "input").mkdir(parents=True)
        with pytest.raises(DatasetError, match=r"(?s)1 photo\(s\) cannot be read.*p2.jpg"):
            stage_photos(photos, tmp_path / "work", "srgb", Console(quiet=True))


class TestExposuresStage:
    def test_records_carry_each_photos_exposure_and_settings(self):
        staged = [
            StagedPhoto(source=Path(f"p{i}.jpg"), name=f"{i:03d}_0.png", exif=exif, raw=False, brightness=0.5)
            for i, exif in enumerate([PhotoExif(exposure_time=0.5, iso=100.0), PhotoExif(), PhotoExif()])
        ]
        photos, reference = photo_records(staged, {"p1.jpg": 0.25}, 0.125, Path("e.csv"))
        assert [(p.source, p.name, p.exposure, p.exposure_source) for p in photos] == [
            ("p0.jpg", "000_0.png", 0.5, "exif"),
            ("p1.jpg", "001_0.png", 0.25, "csv"),
            ("p2.jpg", "002_0.png", 0.125, "flag"),
        ]
        assert photos[0].iso == 100.0 and reference == {"iso": None, "f_number": None}


class TestSfmStage:
    def test_matcher_choice(self):
        assert choose_matcher("auto", 80) == "exhaustive" and choose_matcher("auto", 81) == "sequential"
        assert choose_matcher("sequential", 3) == "sequential"

    def test_mapper_choice(self):
        assert choose_mappers("auto") == ("incremental", "incremental-forward", "global") == MAPPERS
        assert choose_mappers("global") == ("global",)

    def test_best_attempt_places_most_then_fits_best(self):
        attempts = [
            MapperAttempt("incremental", 2, 0.3, 1.0),
            MapperAttempt("incremental-forward", 28, 0.6, 1.0),
            MapperAttempt("global", 28, 0.5, 1.0),
        ]
        assert best_attempt(attempts) == 2  # a tie in photos placed: the lower reprojection error
        attempts[2].placed = 27
        assert best_attempt(attempts) == 1  # more photos beat a lower error
        assert best_attempt([MapperAttempt("incremental", 0, None, 1.0)]) is None

    def test_placed_photos_are_marked_and_the_others_reported(self, tmp_path):
        placed = {"000_0.png", "001_0.png", "002_0.png"}
        model = SimpleNamespace(
            images={i: SimpleNamespace(name=f"{i:03d}_0.png", has_pose=f"{i:03d}_0.png" in placed) for i in range(4)}
        )
        photos = [record(i) for i in range(4)]
        mark_registered(photos, model)
        assert [photo.registered for photo in photos] == [True, True, True, False]
        placed_by = Reconstruction(model=model, matcher="exhaustive", groups=1)
        notes = check_registered(ProcessDataConfig(images=tmp_path, out=tmp_path / "out"), photos, placed_by)
        assert notes == ["1 photo(s) could not be placed and are left out: p3.jpg"]
        assert (
            check_registered(
                ProcessDataConfig(images=tmp_path, out=tmp_path / "out"), photos, placed_by, merged={"p3.jpg"}
            )
            == []
        )


def textured_radiance(height: int = 48, width: int = 64) -> np.ndarray:
    """Linear radiance in about [0.02, 0.3]: a gradient with noise, so bracket members line up."""
    rng = np.random.default_rng(3)
    gradient = np.linspace(0.02, 0.2, width)[None, :, None] * np.ones((height, 1, 3))
    return gradient * (1.0 + 0.5 * rng.random((height, width, 3)))


class TestBracketsStage:
    @pytest.fixture
    def bracket(self, tmp_path):
        """Photos 0-2: one viewpoint at 1, 2 and 4 s (sRGB PNGs of one scene); photo 3: a single at 2 s."""
        radiance = textured_radiance()
        exposures = [1.0, 2.0, 4.0, 2.0]
        staged, photos = [], []
        for i, exposure in enumerate(exposures):
            pixels = encode(np.clip(radiance * exposure, 0, 1), "srgb")
            path = tmp_path / f"p{i}.png"
            write_png(path, pixels)
            staged.append(
                StagedPhoto(
                    source=path,
                    name=f"{i:03d}_0.png",
                    exif=PhotoExif(),
                    raw=False,
                    brightness=float(np.round(pixels * 255).mean() / 255),
                )
            )
            photos.append(record(i, exposure, registered=True))
        return radiance, staged, photos

    def test_a_bracket_is_planned_marked_and_merged(self, bracket):
        radiance, staged, photos = bracket
        plans, notes = plan_brackets([[0, 1, 2], [3]], photos, staged, "srgb", Console(quiet=True))
        assert notes == [] and len(plans) == 1
        plan = plans[0]
        assert plan.members == [0, 1, 2] and plan.exposures == [1.0, 2.0, 4.0] and not plan.estimated
        assert plan.view == 1  # as bright as the single photo
        hdr_views = mark_views(photos, plans)
        assert [(p.view, p.bracket, p.bracket_exposure) for p in photos] == [
            (False, 0, 1.0),
            (True, 0, 2.0),
            (False, 0, 4.0),
            (True, None, None),
        ]
        assert hdr_views == [
            HdrView(
                name="001_0.png",
                sources=["p0.jpg", "p1.jpg", "p2.jpg"],
                exposures=[1.0, 2.0, 4.0],
                exposures_estimated=False,
            )
        ]
        hdr = merge_plan(plan, staged, response_curve("srgb"), "srgb", hdr_views[0].sources)
        assert hdr.shape == radiance.shape
        assert np.median(np.abs(hdr / radiance - 1)) < 0.03  # in units of the darkest member's exposure

    def test_an_unplaced_set_is_not_planned(self, bracket):
        _, staged, photos = bracket
        for photo in photos[:3]:
            photo.registered = False
        assert plan_brackets([[0, 1, 2], [3]], photos, staged, "srgb", Console(quiet=True)) == ([], [])


def staged_photos(folder: Path, images: list[np.ndarray], exposures: list[float | None]):
    """Each linear image through the sRGB curve as a PNG: staged photos and placed records."""
    staged, photos = [], []
    for i, (image, exposure) in enumerate(zip(images, exposures)):
        pixels = encode(np.clip(image, 0, 1), "srgb")
        write_png(folder / f"p{i}.png", pixels)
        brightness = float(np.round(pixels * 255).mean() / 255)
        staged.append(StagedPhoto(folder / f"p{i}.png", f"{i:03d}_0.png", PhotoExif(), False, brightness))
        photos.append(record(i, exposure, registered=True))
    return staged, photos


class TestBracketsAreOneViewpoint:
    """Issue 33: neighbouring viewpoints, one exposure each and no exposure times, are never merged
    and no response is fitted from them; a real bracket still is."""

    def test_single_exposures_of_neighbouring_viewpoints_are_not_merged(self, tmp_path):
        wide = textured_radiance(48, 70)  # a step sideways: the same scene 3 px further on
        staged, photos = staged_photos(tmp_path, [wide[:, :64], 1.04 * wide[:, 3:67]], [None, None])
        plans, notes = plan_brackets([[0, 1]], photos, staged, "srgb", Console(quiet=True))
        assert plans == [] and notes == [
            "p0.jpg, p1.jpg: taken as one viewpoint, but their pixels do not line up in place (another viewpoint, "
            "or something moved): not merged"
        ]
        assert bracket_response(plans, staged, "srgb", Console(quiet=True)) == (None, None, [])

    def test_one_viewpoint_1_04x_apart_is_no_bracket(self, tmp_path):
        radiance = textured_radiance()
        staged, photos = staged_photos(tmp_path, [radiance, 1.04 * radiance], [None, None])
        plans, notes = plan_brackets([[0, 1]], photos, staged, "srgb", Console(quiet=True))
        assert plans == [] and len(notes) == 1
        assert notes[0].startswith("p0.jpg, p1.jpg: one viewpoint, but their exposures span only 0.06 stops")

    def test_a_real_bracket_is_merged_and_its_response_recovered(self, tmp_path):
        scene = textured_radiance(96, 128) ** 2.5 * 40  # about 11 stops: dark and bright parts
        staged, photos = staged_photos(tmp_path, [scene * t for t in (0.25, 1.0, 4.0)], [None] * 3)
        plans, notes = plan_brackets([[0, 1, 2]], photos, staged, "srgb", Console(quiet=True))
        assert notes == [] and [plan.members for plan in plans] == [[0, 1, 2]] and plans[0].estimated
        np.testing.assert_allclose(np.array(plans[0].exposures) / plans[0].exposures[0], [1, 4, 16], rtol=0.03)
        response, source, response_notes = bracket_response(plans, staged, "srgb", Console(quiet=True))
        assert source.startswith("recovered from 1 bracket set(s)") and response_notes == []
        srgb = decode(np.linspace(0, 1, 256), "srgb")
        assert np.abs(np.log(response[20:250] / srgb[20:250, None])).max() < 0.25

    def test_a_response_the_bracket_cannot_carry_falls_back_to_srgb(self, tmp_path):
        radiance = textured_radiance()  # about 4 stops: too few code values for a curve
        staged, photos = staged_photos(tmp_path, [radiance, 2 * radiance], [1.0, 2.0])
        plans, _ = plan_brackets([[0, 1]], photos, staged, "srgb", Console(quiet=True))
        response, source, notes = bracket_response(plans, staged, "srgb", Console(quiet=True))
        np.testing.assert_array_equal(response, np.stack([decode(np.linspace(0, 1, 256), "srgb")] * 3, -1))
        assert source.startswith("srgb (default")
        assert len(notes) == 1 and notes[0].startswith("camera response not fitted (code values well exposed")
        assert "shoot brackets of 3 or more exposures" in notes[0]

    def test_the_assumption_is_said(self):
        photos = [record(i, None, registered=True, view=True) for i in range(3)]
        assert exposure_warnings(photos, {"iso": None, "f_number": None}) == [
            "no exposure times (EXIF, --exposure-csv, --exposure): treating every photo as one unknown exposure "
            "that training learns per view (--learn-exposure), and merging only photos of one viewpoint that line "
            "up, their ratios measured from the pixels; pass --exposure SECONDS or --exposure-csv FILE to give them"
        ]


class TestLayoutStage:
    def test_metadata_files(self, tmp_path):
        model = pycolmap.Reconstruction()
        model.add_camera(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 10.0, 40, 30))
        photos = [record(0, view=True), record(1, view=True, bracket=0), record(2, view=False), record(3, view=True)]
        response = response_curve("srgb")
        config = ProcessDataConfig(images=tmp_path, out=tmp_path / "out", downscale=2, test_every=2)
        assert write_metadata(config, model, photos, response, tmp_path / "d") == ["000_0.png"]
        assert json.loads((tmp_path / "d" / "exposures.json").read_text()) == {
            "000_0.png": 0.01,
            "001_0.png": 0.01,
            "003_0.png": 0.01,
        }
        assert json.loads((tmp_path / "d" / "splits.json").read_text()) == {"test": ["000_0.png"]}
        assert len(json.loads((tmp_path / "d" / "camera_response.json").read_text())["linear_rgb"]) == 256
        written = pycolmap.Reconstruction(tmp_path / "d" / "sparse" / "0")
        assert written.cameras[1].width == 20 and list(written.cameras[1].params) == [5.0, 5.0, 10.0, 7.5]

    def test_white_balance_file_where_exif_has_the_mode(self, tmp_path):
        model = pycolmap.Reconstruction()
        model.add_camera(pycolmap.Camera.create_from_model_name(1, "PINHOLE", 10.0, 40, 30))
        config = ProcessDataConfig(images=tmp_path, out=tmp_path / "out", test_every=2)
        photos = [record(0, view=True, white_balance="auto"), record(1, view=True), record(2, white_balance="auto")]
        write_metadata(config, model, photos, None, tmp_path / "d")
        written = json.loads((tmp_path / "d" / "white_balance.json").read_text())
        assert written == {"000_0.png": "auto", "001_0.png": None}
        write_metadata(config, model, [record(0, view=True)], None, tmp_path / "e")
        assert not (tmp_path / "e" / "white_balance.json").exists()

    def test_test_views_are_every_nth_single(self):
        photos = [record(i, view=True, bracket=0 if i == 1 else None) for i in range(6)]
        assert choose_test_views(photos, 2) == ["000_0.png", "003_0.png", "005_0.png"]  # 001 is bracketed

    def test_install_replaces_the_old_dataset(self, tmp_path):
        (tmp_path / "new").mkdir()
        (tmp_path / "new" / "a").write_text("new")
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "b").write_text("old")
        with pytest.raises(DatasetError, match="appeared while processing"):
            install(tmp_path / "new", tmp_path / "out", overwrite=False)
        install(tmp_path / "new", tmp_path / "out", overwrite=True)
        assert sorted(path.name for path in tmp_path.iterdir()) == ["out"]
        assert [path.name for path in (tmp_path / "out").iterdir()] == ["a"]


class TestReportStage:
    def test_json_and_printed_summary(self, tmp_path):
        photos = [
            record(0, 1 / 60, registered=True, view=True),
            record(1, 1 / 15, registered=True, view=True),
            record(2, 1 / 30),
        ]
        report = ProcessReport(
            out=tmp_path / "mine",
            photos=photos,
            camera_model="PINHOLE",
            width=40,
            height=30,
            matcher="exhaustive",
            mean_reprojection_error=0.5,
            num_points=100,
            test_views=["000_0.png"],
            warnings=["a note"],
            mapper="global",
            mapper_attempts=[MapperAttempt("incremental", 0, None, 1.0), MapperAttempt("global", 2, 0.5, 1.0)],
            gps_rms_m=4.26,
        )
        data = report.to_json()
        assert data["failed"] == ["p2.jpg"] and data["exposure_range"] == (1 / 60, 1 / 15)
        assert data["out"] == str(tmp_path / "mine") and data["exposures_known"]
        stream = io.StringIO()
        print_report(report, Console(file=stream, width=200))
        text = stream.getvalue()
        assert (
            "placed 2 / 3 photos (exhaustive matching, global mapper; placed by each: incremental 0, global 2), "
            "100 points, mean reprojection error 0.500 px" in text
        )
        assert "camera positions against the photos' GPS: 4.3 m RMS after a similarity fit" in text
        assert data["mapper_attempts"][1] == {
            "mapper": "global",
            "placed": 2,
            "mean_reprojection_error": 0.5,
            "seconds": 1.0,
        }
        assert "exposures 0.0166667 s to 0.0666667 s (2.0 stops)" in text
        assert "2 views: 0 HDR (merged brackets), 2 single-exposure LDR; 1 held out for testing" in text
        assert "warning: a note" in text and "left out (not placed): p2.jpg" in text
        assert f"next: mono-hdr train gs --data {tmp_path / 'mine'} --out outputs/mine" in text


class TestGpsCheck:
    def test_degrees_to_local_metres(self):
        # one arc-second of latitude is 30.9 m (a quarter of the WGS 84 equator over 90 * 3600);
        # one of longitude at 60 degrees north half of that
        second = 1 / 3600
        positions = np.array([[60.0, 10.0, 5.0], [60.0 + second, 10.0, 5.0], [60.0, 10.0 + second, 9.0]])
        metres = gps_metres(positions)
        arc_second = 6_378_137.0 * np.pi / 180 / 3600
        assert np.allclose(metres[1] - metres[0], [0.0, arc_second, 0.0], atol=1e-3)
        assert np.allclose(metres[2] - metres[0], [arc_second * 0.5, 0.0, 4.0], atol=2e-3)

    @staticmethod
    def placed(centres, gps):
        images = {
            i: SimpleNamespace(name=f"{i}.png", has_pose=True, projection_center=lambda c=c: np.asarray(c, float))
            for i, c in enumerate(centres)
        }
        staged = [SimpleNamespace(name=f"{i}.png", exif=PhotoExif(gps=g)) for i, g in enumerate(gps)]
        return SimpleNamespace(images=images), staged

    def test_similar_layout_fits_to_the_gps_error(self):
        # a street walk 100 m north and 20 m east; the model is at 1/50 scale, rotated and shifted
        rng = np.random.default_rng(0)
        east_north = np.stack([np.linspace(0, 20, 10), np.linspace(0, 100, 10), np.zeros(10)], -1)
        east_north[:, 2] = rng.normal(0, 0.5, 10)
        to_degrees = 180 / np.pi / 6_378_137.0
        latitude = 55.0 + east_north[:, 1] * to_degrees
        longitude = 13.0 + east_north[:, 0] * to_degrees / np.cos(np.radians(55.0))
        gps = list(zip(latitude, longitude, 30.0 + east_north[:, 2]))
        turn = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        centres = (east_north / 50.0) @ turn.T + [3.0, -1.0, 2.0]
        model, staged = self.placed(centres, gps)
        assert gps_rms_metres(model, staged) < 0.05
        # the same with one camera 10 m off along the street: RMS about 10 / sqrt(10), less the fit's share
        centres[4] += turn @ np.array([0.0, 10.0, 0.0]) / 50.0
        model, staged = self.placed(centres, gps)
        assert 2.0 < gps_rms_metres(model, staged) < 3.2

    def test_without_enough_gps_there_is_no_figure(self):
        model, staged = self.placed([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [(55.0, 13.0, 0.0), None, (55.1, 13.0, 0.0)])
        assert gps_rms_metres(model, staged) is None
        model, staged = self.placed([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [(55.0, 13.0, 0.0)] * 3)
        assert gps_rms_metres(model, staged) is None  # one spot: no direction to fit
