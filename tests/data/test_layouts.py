"""Dataset layouts: round trips, camera conventions, exposures, ordering and bad input."""

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from mono_hdr_plugin.apps.studio.commands import SynthConfig, synth
from mono_hdr_plugin.core.cameras import OPENGL_TO_OPENCV, Camera, look_at
from mono_hdr_plugin.data.captures import CapturedScene, CapturedView, Shot, constant
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError, MissingFileError
from mono_hdr_plugin.data.io import write_png
from mono_hdr_plugin.data.layouts import detect_layout, read_layout, writable_layouts, write_layout
from mono_hdr_plugin.data.layouts.common import natural_key
from mono_hdr_plugin.data.layouts.llff import llff_to_opencv, opencv_to_llff
from mono_hdr_plugin.data.loading import load_scene

WIDTH, HEIGHT, VIEWS = 16, 12, 12
BRACKET_LAYOUTS = ["hdr-gs", "hdr-nerf-synthetic", "hdr-nerf-real"]
"""The layouts that keep every exposure of a view and the scene's split (llff and nerfstudio hold one
photo a view: test_real_layouts.py)."""
EXPOSURES = (0.125, 0.5, 2.0, 8.0, 32.0)
POINT = torch.tensor([[0.2, -0.1, 0.3]])


def make_scene(views=VIEWS) -> CapturedScene:
    rng = np.random.default_rng(0)
    captured = []
    for index in range(views):
        angle = 2 * math.pi * index / views
        eye = torch.tensor([3 * math.cos(angle), 3 * math.sin(angle), 1.0 + 0.1 * index])
        focal = WIDTH / (2 * math.tan(math.radians(25)))
        camera = Camera(
            c2w=look_at(eye, torch.zeros(3)),
            fx=focal,
            fy=focal,
            cx=WIDTH / 2,
            cy=HEIGHT / 2,
            width=WIDTH,
            height=HEIGHT,
            near=0.5,
            far=6.0,
        )
        shots = [
            Shot(t, constant(np.round(rng.random((HEIGHT, WIDTH, 3)) * 255).astype(np.float32) / 255), f"{index}_{e}")
            for e, t in enumerate(EXPOSURES)
        ]
        hdr = (rng.random((HEIGHT, WIDTH, 3)) * 1000).astype(np.float32)
        captured.append(CapturedView(index, camera, "train" if index % 2 == 0 else "test", shots, constant(hdr)))
    points = torch.tensor(rng.random((20, 3)), dtype=torch.float32)
    return CapturedScene(
        "toy", captured, torch.full((3,), -1.0), torch.full((3,), 1.0), points, torch.full((20, 3), 0.5)
    )


def by_split(scene):
    return sorted(scene.views, key=lambda v: (v.split, v.view_id))


@pytest.fixture(scope="module")
def toy():
    return make_scene()


@pytest.fixture
def written(tmp_path, toy, request):
    write_layout(toy, tmp_path / "scene", request.param)
    return tmp_path / "scene"


@pytest.fixture
def written_nerf(tmp_path, toy):
    write_layout(toy, tmp_path / "nerf", "hdr-nerf-synthetic")
    return tmp_path / "nerf"


class TestRoundTrip:
    def test_bracket_layouts_are_writable(self):
        assert set(BRACKET_LAYOUTS) <= set(writable_layouts())

    @pytest.mark.parametrize("layout", BRACKET_LAYOUTS)
    def test_same_cameras_exposures_pixels(self, tmp_path, toy, layout):
        write_layout(toy, tmp_path / layout, layout)
        assert detect_layout(tmp_path / layout) == layout
        back = read_layout(tmp_path / layout)
        assert len(back.views) == len(toy.views)
        for original, loaded in zip(by_split(toy), by_split(back)):
            assert original.split == loaded.split
            torch.testing.assert_close(loaded.camera.c2w, original.camera.c2w, atol=1e-5, rtol=0)
            assert loaded.camera.fx == pytest.approx(original.camera.fx)
            assert [s.exposure for s in loaded.shots] == list(EXPOSURES)
            for a, b in zip(original.shots, loaded.shots):
                assert np.array_equal(a.image(), b.image())
            if layout != "hdr-nerf-real":  # the real layout has no HDR ground truth
                assert np.array_equal(loaded.hdr(), original.hdr())

    def test_hdr_gs_points(self, tmp_path, toy):
        write_layout(toy, tmp_path / "gs", "hdr-gs")
        back = read_layout(tmp_path / "gs")
        torch.testing.assert_close(back.points, toy.points)
        assert back.point_colors.shape == (20, 3)

    @pytest.mark.parametrize("unbounded", [True, False])
    def test_hdr_nerf_synthetic_keeps_the_unbounded_flag(self, tmp_path, toy, unbounded):
        """Written as instant-ngp's aabb_scale (16 for an unbounded scene, absent otherwise)."""
        scene = dataclasses.replace(toy, metadata={"unbounded": unbounded})
        write_layout(scene, tmp_path / "nerf", "hdr-nerf-synthetic")
        for split in ("train", "test"):
            transforms = json.loads((tmp_path / "nerf" / f"transforms_{split}.json").read_text())
            assert transforms.get("aabb_scale") == (16 if unbounded else None)
        # absent: the file declares nothing either way
        assert read_layout(tmp_path / "nerf").metadata["declared_unbounded"] is (True if unbounded else None)

    @pytest.mark.parametrize("scale, unbounded", [(1, False), (4, True)])
    def test_aabb_scale_of_other_tools_is_read(self, written_nerf, scale, unbounded):
        """Read as a declaration: the photos decide (tests/data/test_extent.py)."""
        transforms_file = written_nerf / "transforms_train.json"
        transforms = json.loads(transforms_file.read_text())
        transforms_file.write_text(json.dumps({**transforms, "aabb_scale": scale}))
        assert read_layout(written_nerf).metadata["declared_unbounded"] is unbounded

    def test_bad_aabb_scale_names_the_file(self, written_nerf):
        transforms_file = written_nerf / "transforms_test.json"
        transforms_file.write_text(json.dumps({**json.loads(transforms_file.read_text()), "aabb_scale": -2}))
        with pytest.raises(DatasetError, match=r"transforms_test.json: aabb_scale must be"):
            read_layout(written_nerf)


class TestCameraConversions:
    @pytest.mark.parametrize("layout", BRACKET_LAYOUTS)
    def test_known_point_projects_to_same_pixel(self, tmp_path, toy, layout):
        write_layout(toy, tmp_path / layout, layout)
        for original, loaded in zip(by_split(toy), by_split(read_layout(tmp_path / layout))):
            expected, depth = original.camera.project(POINT)
            got, _ = loaded.camera.project(POINT)
            assert depth.item() > 0
            torch.testing.assert_close(got, expected, atol=1e-3, rtol=0)

    def test_opengl_pose(self):
        """A Blender camera at the origin looking down -z sees +x right and +y up."""
        camera = Camera(c2w=torch.eye(4) @ OPENGL_TO_OPENCV, fx=10, fy=10, cx=8, cy=6, width=16, height=12)
        pixel, depth = camera.project(torch.tensor([[1.0, 1.0, -10.0]]))
        assert depth.item() == pytest.approx(10) and pixel[0, 0] > 8 and pixel[0, 1] < 6

    def test_llff_pose(self):
        """LLFF columns are (down, right, back): with down = -y, right = +x it looks down -z."""
        llff = np.array([[0, 1, 0, 0], [-1, 0, 0, 0], [0, 0, 1, 0]], dtype=float)
        camera = Camera(
            c2w=torch.from_numpy(llff_to_opencv(llff)).float(), fx=10, fy=10, cx=8, cy=6, width=16, height=12
        )
        pixel, depth = camera.project(torch.tensor([[1.0, 1.0, -10.0]]))
        assert depth.item() == pytest.approx(10) and pixel[0, 0] > 8 and pixel[0, 1] < 6
        assert np.allclose(opencv_to_llff(llff_to_opencv(llff)), llff)


class TestHdrNerfSynthetic:
    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_files_follow_the_official_names(self, written):
        frames = json.loads((written / "transforms_train.json").read_text())["frames"]
        assert frames[0]["file_path"] == "./train/r_0"
        exposures = json.loads((written / "exposure_train.json").read_text())
        assert exposures["./train/r_0_4.png"] == 32.0
        assert (written / "test_hdr" / "hdr_000.exr").is_file()

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_missing_exposure_entry(self, written):
        path = written / "exposure_train.json"
        table = json.loads(path.read_text())
        del table["./train/r_1_2.png"]
        path.write_text(json.dumps(table))
        with pytest.raises(DatasetError, match="exposure_train.json.*no exposure for './train/r_1_2.png'"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    @pytest.mark.parametrize("bad", [0, -1, "fast", None])
    def test_bad_exposure_value(self, written, bad):
        path = written / "exposure_test.json"
        table = json.loads(path.read_text())
        table["./test/r_0_0.png"] = bad
        path.write_text(json.dumps(table))
        with pytest.raises(DatasetError, match="exposure_test.json.*not a positive number"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_exposure_out_of_step_with_images(self, written):
        (written / "train" / "r_2_3.png").unlink()
        with pytest.raises(DatasetError, match="r_2_3.png.*out of step"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_nan_pose(self, written):
        path = written / "transforms_train.json"
        transforms = json.loads(path.read_text())
        transforms["frames"][1]["transform_matrix"][0][3] = float("nan")
        path.write_text(json.dumps(transforms))
        with pytest.raises(DatasetError, match="transforms_train.json.*NaN or Inf"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_missing_transforms(self, written):
        (written / "transforms_test.json").unlink()
        with pytest.raises(MissingFileError, match="transforms_test.json"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_mixed_sizes(self, written):
        write_png(written / "train" / "r_1_0.png", np.zeros((5, 5, 3)))
        with pytest.raises(DatasetError, match="mixed sizes.*resize"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_nan_in_hdr_ground_truth(self, written):
        import OpenEXR

        bad = np.ones((HEIGHT, WIDTH, 3), np.float32)
        bad[0, 0, 0] = np.inf
        OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": bad}).write(str(written / "train_hdr" / "hdr_000.exr"))
        with pytest.raises(DatasetError, match="hdr_000.exr.*NaN or Inf"):
            load_scene(DataConfig(data=written))

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_truncated_png_names_the_file(self, written):
        path = written / "test" / "r_3_2.png"
        path.write_bytes(path.read_bytes()[:60])
        with pytest.raises(DatasetError, match="r_3_2.png"):
            load_scene(DataConfig(data=written))


class TestHdrNerfReal:
    @pytest.mark.parametrize("written", ["hdr-nerf-real"], indirect=True)
    def test_rows_out_of_step(self, written):
        (written / "input_images" / "011_4.png").unlink()
        with pytest.raises(DatasetError, match="poses_bounds_exps.npy.*59 images.*out of step"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-nerf-real"], indirect=True)
    @pytest.mark.parametrize(
        "column,value,message", [(3, np.nan, "NaN or Inf"), (17, 0.0, "not a positive"), (17, -2.0, "not a positive")]
    )
    def test_bad_rows(self, written, column, value, message):
        rows = np.load(written / "poses_bounds_exps.npy")
        rows[7, column] = value
        np.save(written / "poses_bounds_exps.npy", rows)
        with pytest.raises(DatasetError, match=f"poses_bounds_exps.npy.*{message}"):
            read_layout(written)

    def test_numeric_view_order_with_unpadded_names(self, tmp_path):
        """Views 0..11 named without padding: numeric order, whatever the string order."""
        scene = make_scene()
        folder = tmp_path / "real"
        write_layout(scene, folder, "hdr-nerf-real")
        images = folder / "input_images"
        for path in sorted(images.iterdir()):
            view, e = path.stem.split("_")
            path.rename(images / f"{int(view)}_{e}.png")
        # Rows must follow the string-sorted names, as the official loader pairs them.
        rows = np.load(folder / "poses_bounds_exps.npy")
        padded = sorted(f"{v:03d}_{e}" for v in range(VIEWS) for e in range(5))
        unpadded = sorted(f"{v}_{e}" for v in range(VIEWS) for e in range(5))
        reorder = [padded.index("{:03d}_{}".format(*map(int, n.split("_")))) for n in unpadded]
        np.save(folder / "poses_bounds_exps.npy", rows[reorder])
        back = read_layout(folder)
        assert [v.name for v in back.views] == [str(i) for i in range(VIEWS)]
        for original, loaded in zip(scene.views, back.views):
            torch.testing.assert_close(loaded.camera.c2w, original.camera.c2w, atol=1e-5, rtol=0)


class TestHdrGs:
    @pytest.mark.parametrize("written", ["hdr-gs"], indirect=True)
    def test_default_exposures_without_json(self, written):
        (written / "exposures.json").unlink()
        back = read_layout(written)
        assert [s.exposure for s in back.views[0].shots] == list(EXPOSURES)

    @pytest.mark.parametrize("written", ["hdr-gs"], indirect=True)
    def test_exposures_json_overrides(self, written):
        table = json.loads((written / "exposures.json").read_text())
        table = {name: value * 3 for name, value in table.items()}
        (written / "exposures.json").write_text(json.dumps(table))
        assert [s.exposure for s in read_layout(written).views[0].shots] == [3 * t for t in EXPOSURES]

    @pytest.mark.parametrize("written", ["hdr-gs"], indirect=True)
    def test_process_data_style_one_photo_per_view(self, written):
        """exposures.json listing one photo per view at any exposure: each view used as is."""
        table = {f"{v:03d}_0.png": 0.01 * (v + 1) for v in range(VIEWS)}
        (written / "exposures.json").write_text(json.dumps(table))
        data = load_scene(DataConfig(data=written))
        assert len(data.train) == 6 and len(data.test) == 6
        assert [v.exposure for v in data.train] == pytest.approx([0.01 * (v + 1) for v in range(0, VIEWS, 2)])

    @pytest.mark.parametrize("written", ["hdr-gs"], indirect=True)
    def test_missing_exposure_in_json(self, written):
        table = json.loads((written / "exposures.json").read_text())
        del table["000_0.png"]
        (written / "exposures.json").write_text(json.dumps(table))
        with pytest.raises(DatasetError, match="exposures.json.*no exposure for '000_0.png'"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-gs"], indirect=True)
    def test_missing_image(self, written):
        (written / "images" / "004_0.png").unlink()
        with pytest.raises(MissingFileError, match="004_0.png"):
            read_layout(written)

    @pytest.mark.parametrize("written", ["hdr-gs"], indirect=True)
    def test_split_is_numeric_even_views(self, written):
        data = load_scene(DataConfig(data=written))
        assert [v.name for v in data.train] == [f"{v:03d}_2.png" for v in range(0, VIEWS, 2)]
        assert data.points is not None


class TestDetectionAndLoading:
    def test_unknown_layout(self, tmp_path):
        (tmp_path / "photos").mkdir()
        with pytest.raises(DatasetError, match="unknown dataset layout.*process-data"):
            read_layout(tmp_path / "photos")

    def test_missing_folder(self, tmp_path):
        with pytest.raises(MissingFileError, match="nowhere"):
            load_scene(DataConfig(data=tmp_path / "nowhere"))

    def test_bad_layout_name(self, tmp_path):
        with pytest.raises(DatasetError, match="unknown --layout"):
            read_layout(tmp_path, "mipnerf-blender")

    def test_natural_key(self):
        assert sorted(["10_0", "2_0", "1_0"], key=natural_key) == ["1_0", "2_0", "10_0"]

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_load_scene_single_protocol(self, written):
        data = load_scene(DataConfig(data=written, exposure_index=2))
        assert data.train_exposures == [32.0] == data.test_exposures
        assert len(data.train) == 6 and data.train[0].hdr is not None


class TestPartialHdr:
    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic", "hdr-gs"], indirect=True)
    def test_missing_exr_is_named_in_a_warning(self, written):
        exr = sorted(written.rglob("*.exr"))[1]
        exr.unlink()
        with pytest.warns(UserWarning, match=r"1 of 12 views have no HDR ground truth \(.*\); .*Add their EXR"):
            data = load_scene(DataConfig(data=written))
        assert sum(v.hdr is None for v in data.train + data.test) > 0

    @pytest.mark.parametrize("written", ["hdr-nerf-synthetic"], indirect=True)
    def test_complete_or_absent_hdr_is_silent(self, written, recwarn):
        load_scene(DataConfig(data=written))
        for exr in written.rglob("*.exr"):
            exr.unlink()
        data = load_scene(DataConfig(data=written))
        assert all(v.hdr is None for v in data.train + data.test)
        assert not [w for w in recwarn if "HDR ground truth" in str(w.message)]


class TestSynth:
    @pytest.mark.parametrize("layout", ["hdr-nerf-synthetic", "hdr-gs"])
    def test_written_scene_reads_back_identically(self, tmp_path, tiny_demo, layout, monkeypatch):
        from mono_hdr_plugin.apps.studio import scenes
        from mono_hdr_plugin.apps.studio.dataset import studio_captured_scene

        monkeypatch.setitem(scenes.SCENES, "demo", tiny_demo)
        out = synth(SynthConfig(scene="demo", out=tmp_path / layout, layout=layout))
        original = load_scene(DataConfig(scene="demo", protocol="multi"))
        loaded = load_scene(DataConfig(data=out, protocol="multi"))
        for a, b in zip(original.train + original.test, loaded.train + loaded.test):
            torch.testing.assert_close(b.camera.c2w, a.camera.c2w, atol=1e-5, rtol=0)
            assert a.exposure == b.exposure and torch.equal(a.image, b.image) and torch.equal(a.hdr, b.hdr)
        assert len(studio_captured_scene(tiny_demo).views) == 10
