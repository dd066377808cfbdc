"""Degenerate data is refused or warned about, never scored (docs/robustness.md, "Degenerate data"):
HDR ground truth that is all zero, constant or negative, and every numeric field of every dataset
file, each refused with the file and the key named."""

import json
import math
import shutil
import warnings

import numpy as np
import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
import torch
from cli_driver import train_args
from hard_scenes import make_scene, make_trainer, write_disk_scene

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.dataset import View
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_exr, write_exr
from mono_hdr_plugin.data.layouts import read_layout
from mono_hdr_plugin.data.loading import load_scene


@pytest.fixture
def data(tmp_path, disk_scene):
    folder = tmp_path / "scene"
    shutil.copytree(disk_scene, folder)
    return folder


def edit_json(path, edit) -> None:
    value = json.loads(path.read_text())
    edit(value)
    path.write_text(json.dumps(value))


def hdr_files(folder):
    return sorted(folder.glob("*_hdr/hdr_*.exr"))


# ------------------------------------------------------------------ HDR ground truth
def test_all_zero_hdr_ground_truth_is_never_scored(data, tmp_path):
    """The issue's case: zero EXRs trained and reported an HDR PSNR. Now: a warning naming the files,
    the views train on LDR only, and metrics.json has no HDR figures."""
    for path in hdr_files(data):
        write_exr(path, np.zeros_like(read_exr(path)))
    with pytest.warns(
        UserWarning,
        match=r"HDR ground truth of 6 view\(s\) carries no HDR information and is not used "
        r"for training or HDR metrics \(.*train_hdr/hdr_000.exr is all zero",
    ):
        main(train_args(data, tmp_path / "run", 2))
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert all(metrics[key] is None for key in ("hdr_psnr", "hdr_ssim", "hdr_psnr_gt_max", "hdr_ssim_gt_max"))
    assert math.isfinite(metrics["ldr_psnr"])


def test_one_constant_view_is_left_out_and_named(data):
    path = data / "test_hdr" / "hdr_001.exr"
    write_exr(path, np.full_like(read_exr(path), 0.25))
    with pytest.warns(
        UserWarning,
        match=r"1 view\(s\).*test_hdr/hdr_001.exr has one value \(0.25, 0.25, 0.25\) at "
        "every pixel",
    ):
        scene = load_scene(DataConfig(data=data))
    assert [v.hdr is None for v in scene.test] == [False, True, False]


def test_negative_hdr_ground_truth_is_refused_naming_the_file(data):
    path = data / "train_hdr" / "hdr_002.exr"
    pixels = read_exr(path)
    pixels[3:5, 3:5] = -pixels[3:5, 3:5]
    write_exr(path, pixels)
    with pytest.raises(
        DatasetError,
        match=r"train_hdr/hdr_002.exr: HDR ground truth has 4 pixel\(s\) with negative "
        r"values \(down to -\d.*\); radiance is never negative",
    ):
        load_scene(DataConfig(data=data))


def test_in_memory_scenes_are_held_to_the_same_rules():
    with pytest.warns(UserWarning, match=r"scene 'hard': the HDR ground truth of 6 view\(s\).*is all zero"):
        scene = make_scene(hdr_transform=lambda hdr, i: torch.zeros_like(hdr))
    assert all(v.hdr is None for v in scene.train + scene.test)
    view = scene.train[0]
    with pytest.raises(DatasetError, match="hard_000: HDR ground truth has 256 pixel"):
        View(
            camera=view.camera,
            image=view.image,
            exposure=view.exposure,
            view_id=0,
            name=view.name,
            hdr=-torch.ones(16, 16, 3),
        )


@pytest.mark.parametrize("target", ["zeros", "constant"])
def test_a_flat_region_under_a_ray_batch_keeps_the_hdr_loss_finite(tmp_path, target):
    """Degenerate targets still reach the loss inside a batch (a flat region of a valid image): finite."""
    scene = make_scene()
    trainer = make_trainer(tmp_path, "nerf", scene, max_steps=20)
    for view in scene.train:  # past SceneData's check, as a ray batch inside one flat region would be
        view.hdr = torch.zeros_like(view.hdr) if target == "zeros" else torch.full_like(view.hdr, 3.0)
    for _ in range(20):
        record = trainer.train_step()
        assert not record["skipped"] and math.isfinite(record["loss"]), record


# ------------------------------------------------------------------ every numeric field of every dataset file
TRANSFORMS_CASES = [
    ("camera_angle_x", 0, r"camera_angle_x \(field of view, radians\) must be a number in \(0, 3.14159\), got 0"),
    ("camera_angle_x", None, r"camera_angle_x .* got None"),
    ("camera_angle_x", "0.69", r"camera_angle_x .* got '0.69'"),
    ("camera_angle_x", 3.5, r"camera_angle_x .* got 3.5"),
    ("camera_angle_x", True, r"camera_angle_x .* got True"),
    ("camera_angle_x", 1e400, r"camera_angle_x .* got inf \(NaN or Inf\)"),
    ("matrix", None, r"frames\[1\].transform_matrix must be a 4x4 list of rows of numbers, got None"),
    ("matrix", [[1, 0, 0], [0, 1, 0], [0, 0, 1]], r"frames\[1\].transform_matrix must be a 4x4"),
    ("matrix entry", "1", r"frames\[1\].transform_matrix\[0\]\[3\] must be a finite number, got '1'"),
    ("matrix entry", math.nan, r"frames\[1\].transform_matrix\[0\]\[3\] must be a finite number, got nan"),
    ("file_path", 7, r"frames\[1\].file_path must be a non-empty file name, got 7"),
    ("file_path", "", r"frames\[1\].file_path must be a non-empty file name, got ''"),
    ("file_path", "./train/r_\ud800", r"frames\[1\].file_path '\./train/r_\\ud800' is not a valid file name"),
    ("frame", "r_1", r"frames\[1\] must be a JSON object \{...\}, got 'r_1'"),
    ("frames", {"0": {}}, r"needs 'camera_angle_x' and a non-empty 'frames' list"),
]


@pytest.mark.parametrize("key,value,message", TRANSFORMS_CASES, ids=[f"{k}={v!r}" for k, v, _ in TRANSFORMS_CASES])
def test_transforms_fields_are_refused_naming_file_and_key(data, key, value, message):
    def edit(transforms):
        if key == "camera_angle_x":
            transforms["camera_angle_x"] = value
        elif key == "matrix":
            transforms["frames"][1]["transform_matrix"] = value
        elif key == "matrix entry":
            transforms["frames"][1]["transform_matrix"][0][3] = value
        elif key == "file_path":
            transforms["frames"][1]["file_path"] = value
        elif key == "frame":
            transforms["frames"][1] = value
        else:
            transforms["frames"] = value

    edit_json(data / "transforms_train.json", edit)
    with pytest.raises(DatasetError, match=rf"transforms_train.json: {message}"):
        load_scene(DataConfig(data=data))


@pytest.mark.parametrize("value", [None, "x", True, -1, 0, 1e400, [2.0], {"t": 2}])
def test_exposure_values_are_refused_naming_file_and_image(data, value):
    edit_json(data / "exposure_test.json", lambda table: table.update({"./test/r_1_3.png": value}))
    with pytest.raises(
        DatasetError,
        match=r"exposure_test.json \['./test/r_1_3.png'\]: exposure time .* is not a "
        "positive number of seconds",
    ):
        load_scene(DataConfig(data=data))


@pytest.mark.parametrize("document", ["[]", '"x"', "null", "1e99999", "[" * 100_000])
def test_json_that_is_not_an_object_or_cannot_be_read(data, document):
    (data / "exposure_train.json").write_text(document)
    with pytest.raises(DatasetError, match="exposure_train.json( must be a JSON object|: not valid JSON)"):
        load_scene(DataConfig(data=data))


def test_huge_integer_is_invalid_json_not_a_crash(data):
    (data / "exposure_train.json").write_text('{"./train/r_0_0.png": ' + "9" * 5000 + "}")
    with pytest.raises(DatasetError, match=r"exposure_train.json: not valid JSON \(Exceeds the limit"):
        load_scene(DataConfig(data=data))


@pytest.fixture
def real(tmp_path):
    folder = tmp_path / "real"
    write_disk_scene(folder, layout="hdr-nerf-real")
    return folder


@pytest.mark.parametrize(
    "column,value,message",
    [
        (4, 0.0, r"image height, width and focal length \(columns 4, 9 and 14\) must be positive, got 0, "),
        (9, -16.0, r"must be positive, got 16, -16, "),
        (14, 0.0, r"must be positive, got 16, 16, 0"),
        (15, math.inf, "NaN or Inf"),
        (16, math.nan, "NaN or Inf"),
        (17, 0.0, "exposure time 0.0 is not a positive number"),
    ],
)
def test_poses_bounds_fields_are_refused_naming_the_file(real, column, value, message):
    rows = np.load(real / "poses_bounds_exps.npy")
    rows[0, column] = value
    np.save(real / "poses_bounds_exps.npy", rows)
    with pytest.raises(DatasetError, match=f"poses_bounds_exps.npy.*{message}"):
        read_layout(real)


def test_poses_bounds_that_are_not_numbers(real):
    np.save(real / "poses_bounds_exps.npy", np.array([["a"] * 18] * 30))
    with pytest.raises(DatasetError, match="poses_bounds_exps.npy: a pose, bound or exposure is not numeric"):
        read_layout(real)


@pytest.fixture
def colmap_text(tmp_path):
    """An HDR-GS dataset whose COLMAP model is in text form."""
    import pycolmap  # after PIL has written the images (see write_disk_scene)

    folder = tmp_path / "gs"
    write_disk_scene(folder, layout="hdr-gs")
    model = folder / "sparse" / "0"
    pycolmap.Reconstruction(str(model)).write_text(str(model))
    for binary in model.glob("*.bin"):
        binary.unlink()
    return folder


def replace_line(path, index, text):
    lines = path.read_text().splitlines()
    data_lines = [i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")]
    lines[data_lines[index]] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "file,line,text,message",
    [
        (
            "cameras.txt",
            0,
            "1 PINHOLE 16 16 0 17.6 8 8",
            r"cameras.txt line 4: PARAMS\[0\] \(focal length\) must be a "
            r"positive number, got '0'",
        ),
        ("cameras.txt", 0, "1 PINHOLE 16 16 nan 17.6 8 8", r"line 4: PARAMS\[0\] .* got 'nan'"),
        (
            "cameras.txt",
            0,
            "1 PINHOLE 16 16 17.6 17.6 8 inf",
            r"line 4: PARAMS\[3\] must be a finite number, got 'inf'",
        ),
        (
            "cameras.txt",
            0,
            "1 PINHOLE -16 16 17.6 17.6 8 8",
            r"line 4: WIDTH must be an integer from 1 to 1000000, got "
            r"'-16'",
        ),
        ("cameras.txt", 0, "1 PINHOLE 16 16 17.6 17.6 8", "camera model PINHOLE has 4 parameters, the line has 3"),
        ("cameras.txt", 0, "1 FISHEYE 16 16 17.6", "MODEL 'FISHEYE' is not a COLMAP camera model"),
        (
            "images.txt",
            0,
            "1 0 0 0 0 0 0 3 1 000_0.png",
            "images.txt line 5: the rotation quaternion QW QX QY QZ is zero",
        ),
        (
            "images.txt",
            0,
            "1 1 0 0 0 0 0 three 1 000_0.png",
            "images.txt line 5: TZ must be a finite number, got 'three'",
        ),
        ("images.txt", 0, "1 1 0 0 0 0 0 3 7 000_0.png", "images.txt line 5: CAMERA_ID 7 is not in cameras.txt"),
        ("images.txt", 0, "1 1 0 0 0 0 0 3 1", "images.txt line 5: NAME is missing"),
        ("images.txt", 1, "1 1 0 0 0 0 0 3 1 001_0.png", "images.txt line 7: IMAGE_ID 1 appears twice"),
        ("points3D.txt", None, "1 0 nan 0 255 0 0 0.5", "points3D.txt line 4: Y must be a finite number, got 'nan'"),
        (
            "points3D.txt",
            None,
            "1 0 0 0 300 0 0 0.5",
            "points3D.txt line 4: R must be an integer from 0 to 255, got '300'",
        ),
    ],
)
def test_colmap_text_fields_are_refused_naming_file_line_and_field(colmap_text, file, line, text, message):
    path = colmap_text / "sparse" / "0" / file
    if line is None:
        path.write_text(path.read_text() + text + "\n")
    else:
        replace_line(path, line, text)
    with pytest.raises(DatasetError, match=message):
        read_layout(colmap_text)


def test_exposures_json_of_hdr_gs_is_checked(colmap_text):
    (colmap_text / "exposures.json").write_text('{"000_0.png": "soon"}')
    with pytest.raises(DatasetError, match=r"exposures.json \['000_0.png'\]: exposure time 'soon' is not a positive"):
        read_layout(colmap_text)
    (colmap_text / "exposures.json").write_text("[0.5, 2]")
    with pytest.raises(DatasetError, match=r"exposures.json must be a JSON object"):
        read_layout(colmap_text)


def test_colmap_points_with_nan_are_left_out_with_a_warning(colmap_text):
    path = colmap_text / "sparse" / "0" / "points3D.txt"
    path.write_text(path.read_text() + "1 0.1 0.2 0.3 255 0 0 0.5\n2 0.4 0.5 0.6 0 255 0 0.5\n")
    import pycolmap

    model = pycolmap.Reconstruction(str(path.parent))
    model.points3D[2].xyz = np.array([np.nan, 0.0, 0.0])
    model.write(str(path.parent))  # binary: the text check cannot see it; the reader must
    with pytest.warns(UserWarning, match=r"1 of 2 COLMAP points have NaN/Inf coordinates"):
        scene = read_layout(colmap_text)
    assert scene.points.shape == (1, 3)


def test_warnings_do_not_hide_valid_loads(data):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_scene(DataConfig(data=data))
