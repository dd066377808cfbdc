"""The bad-input matrix (issue 8): every malformed input the loaders, the CLI and checkpoints
meet gets an error of a known type whose message names the file or the argument.

Cases already tested elsewhere are not repeated; docs/robustness.md lists every case with the
test that covers it (tests/data/test_io.py, tests/data/test_layouts.py, tests/core/...).
"""

import json
import shutil

import numpy as np
import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
import torch
from hard_scenes import make_scene, make_trainer, write_disk_scene

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.registry import RegistryError, get_backbone
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.io import read_image
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.checkpoints import CheckpointError, load_checkpoint, save_checkpoint
from mono_hdr_plugin.training.trainer import build_trainer


@pytest.fixture
def data(tmp_path, disk_scene):
    """A private copy of the on-disk scene, free to break."""
    folder = tmp_path / "scene"
    shutil.copytree(disk_scene, folder)
    return folder


def train_args(data, out, *extra) -> list[str]:
    return [
        "train",
        "voxel-grid",
        "--data",
        str(data),
        "--out",
        str(out),
        "--quiet",
        "--max-steps",
        "1",
        "--no-save-renders",
        "--max-eval-views",
        "1",
        "--backbone.resolution",
        "4",
        "--backbone.samples-per-ray",
        "4",
        *extra,
    ]


def edit_json(path, edit) -> None:
    value = json.loads(path.read_text())
    edit(value)
    path.write_text(json.dumps(value))


# ---------------------------------------------------------------------------- loaders
def test_empty_image_file_names_it(data):
    (data / "train" / "r_0_1.png").write_bytes(b"")
    with pytest.raises(DatasetError, match="r_0_1.png"):
        load_scene(DataConfig(data=data))


def test_jpeg_cut_mid_scan_names_it(tmp_path):
    from PIL import Image

    path = tmp_path / "photo.jpg"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8)).save(path, quality=95)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(DatasetError, match="photo.jpg.*truncated or corrupt"):
        read_image(path)


def test_exposure_json_not_json_names_it(data):
    (data / "exposure_train.json").write_text("{not json")
    with pytest.raises(DatasetError, match="exposure_train.json: not valid JSON"):
        load_scene(DataConfig(data=data))


def test_infinite_exposure_names_file_and_image(data):
    edit_json(data / "exposure_train.json", lambda table: table.update({"./train/r_0_0.png": float("inf")}))
    with pytest.raises(DatasetError, match=r"exposure_train.json.*r_0_0.png.*not a positive number"):
        load_scene(DataConfig(data=data))


def test_missing_exposure_file_names_it(data):
    (data / "exposure_test.json").unlink()
    with pytest.raises(DatasetError, match="exposure_test.json: file not found"):
        load_scene(DataConfig(data=data))


def test_transforms_without_frames_names_it(data):
    edit_json(data / "transforms_train.json", lambda t: t.update({"frames": []}))
    with pytest.raises(DatasetError, match="transforms_train.json: needs 'camera_angle_x' and a non-empty"):
        load_scene(DataConfig(data=data))


def test_scaled_rotation_in_pose_names_file_and_frame(data):
    edit_json(data / "transforms_train.json", lambda t: t["frames"][1]["transform_matrix"][0].__setitem__(0, 5.0))
    with pytest.raises(DatasetError, match=r"transforms_train.json frame './train/r_1'.*not orthonormal"):
        load_scene(DataConfig(data=data))


def test_negative_field_of_view_names_file(data):
    for split in ("train", "test"):
        edit_json(data / f"transforms_{split}.json", lambda t: t.update({"camera_angle_x": -0.5}))
    with pytest.raises(
        DatasetError,
        match=r"transforms_train.json: camera_angle_x \(field of view, radians\) must "
        r"be a number in \(0, 3.14159\), got -0.5",
    ):
        load_scene(DataConfig(data=data))


def test_real_layout_near_beyond_far_names_the_row(tmp_path):
    from mono_hdr_plugin.data.layouts import read_layout

    folder = tmp_path / "real"
    write_disk_scene(folder, layout="hdr-nerf-real")
    rows = np.load(folder / "poses_bounds_exps.npy")
    rows[:, 15], rows[:, 16] = 5.0, 1.0
    np.save(folder / "poses_bounds_exps.npy", rows)
    with pytest.raises(DatasetError, match=r"poses_bounds_exps.npy row of 000_0.*near <= far"):
        read_layout(folder)


def test_missing_hdr_ground_truth_trains_that_view_on_ldr_only(data):
    """HDR ground truth is optional per view (LDR:HDR ratios): a missing EXR is a warning naming
    the view, not an error."""
    (data / "train_hdr" / "hdr_000.exr").unlink()
    with pytest.warns(UserWarning, match=r"1 of 6 views have no HDR ground truth \(\./train/r_0\)"):
        scene = load_scene(DataConfig(data=data))
    assert scene.train[0].hdr is None and scene.train[1].hdr is not None


# ---------------------------------------------------------------------------- CLI
@pytest.mark.parametrize(
    "flag,value,message",
    [
        ("--hdr-view-ratio", "0:0", "--hdr-view-ratio"),
        ("--hdr-view-ratio", "2", "--hdr-view-ratio must look like 2:1"),
        ("--checkpoint-every", "0", "--checkpoint-every must be an integer >= 1"),
        ("--max-steps", "-1", "--max-steps must be an integer >= 0"),
        ("--eval-every", "-2", "--eval-every must be an integer >= 0"),
        ("--nan-patience", "0", "--nan-patience must be an integer >= 1"),
        ("--max-eval-views", "0", "--max-eval-views must be an integer >= 1"),
        ("--downscale", "0", "--downscale must be a positive integer, got 0"),
        ("--exposure-index", "5", r"--exposure-index must be an integer in \[0, 2\], got 5"),
    ],
)
def test_bad_run_flag_is_refused_before_loading(tmp_path, flag, value, message, monkeypatch):
    import mono_hdr_plugin.data.loading as loading

    monkeypatch.setattr(loading, "load_scene", lambda config: pytest.fail("the scene was loaded first"))
    with pytest.raises(ValueError, match=message):
        main(train_args(tmp_path / "unused", tmp_path / "run", flag, value))


@pytest.mark.parametrize(
    "flag,value,message",
    [
        ("--fixed-exposure", "3", "no photo at 3.0 s.*--fixed-exposure"),
    ],
)
def test_bad_data_flag_names_it(tmp_path, data, flag, value, message):
    extra = ["--protocol", "fixed"] if flag == "--fixed-exposure" else []
    with pytest.raises(DatasetError, match=message):
        main(train_args(data, tmp_path / "run", flag, value, *extra))


def test_fixed_protocol_without_exposure(tmp_path, data):
    with pytest.raises(DatasetError, match="--protocol fixed needs --fixed-exposure"):
        main(train_args(data, tmp_path / "run", "--protocol", "fixed"))


@pytest.mark.parametrize(
    "argv,named",
    [
        (["train", "no-such-backbone"], "no-such-backbone"),
        (["train", "voxel-grid", "--method", "bogus"], "bogus"),
        (["train", "voxel-grid", "--layout", "bogus"], "bogus"),
        (["train", "voxel-grid", "--max-steps", "many"], "many"),
    ],
)
def test_unparseable_cli_value_exits_2_naming_it(argv, named, capsys, monkeypatch):
    from mono_hdr_plugin.apps import cli

    monkeypatch.setattr("sys.argv", ["mono-hdr", *argv])
    monkeypatch.delenv("MONO_HDR_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        cli.run()
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    assert named in captured.out + captured.err


def test_unknown_backbone_through_the_registry():
    with pytest.raises(RegistryError, match="no backbone named 'nope'; available: .*gs.*nerf"):
        get_backbone("nope")


def test_unknown_scene_and_no_scene(tmp_path):
    with pytest.raises(DatasetError, match="unknown scene 'nope'"):
        main(["train", "voxel-grid", "--scene", "nope", "--out", str(tmp_path)])
    with pytest.raises(DatasetError, match="no scene given: pass --data FOLDER or --scene NAME"):
        main(["train", "voxel-grid", "--out", str(tmp_path)])


def test_resume_from_another_backbones_checkpoint(tmp_path):
    scene = make_scene()
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=1)
    trainer.save()
    config = make_trainer(tmp_path, "gs", scene, max_steps=1).config
    config.resume = True
    with pytest.raises(ValueError, match="the checkpoint holds a 'voxel-grid' model, not 'gs'"):
        build_trainer(config, "gs", scene)


@pytest.mark.parametrize("command", ["eval", "render"])
def test_eval_and_render_of_missing_checkpoint(tmp_path, command):
    with pytest.raises(CheckpointError, match="gone.pt does not exist"):
        main([command, "--checkpoint", str(tmp_path / "gone.pt"), "--out", str(tmp_path / "out")])


def test_render_non_positive_exposure_is_refused_before_loading(tmp_path):
    """The exposure check comes first: a missing checkpoint would otherwise be reported instead."""
    with pytest.raises(ValueError, match="--exposures must be a positive number, got 0.0"):
        main(
            [
                "render",
                "--checkpoint",
                str(tmp_path / "not-yet-loaded.pt"),
                "--out",
                str(tmp_path / "r"),
                "--exposures",
                "1",
                "0",
            ]
        )


# ------------------------------------------------------------------------ checkpoints
def test_checkpoint_with_pickled_code_is_refused(tmp_path):
    """weights_only loading: a checkpoint that needs arbitrary unpickling is never executed."""
    path = tmp_path / "evil.pt"
    torch.save({"format": "mono-hdr-3d checkpoint", "format_version": 1, "payload": DatasetError("x")}, path)
    with pytest.raises(CheckpointError, match="evil.pt is not a mono-hdr-3d checkpoint") as error:
        load_checkpoint(path)
    assert "weights_only" not in str(error.value)


def test_other_torch_file_is_not_a_checkpoint(tmp_path):
    path = tmp_path / "weights.pt"
    torch.save({"weights": torch.zeros(3)}, path)
    with pytest.raises(CheckpointError, match="weights.pt is not a mono-hdr-3d checkpoint"):
        load_checkpoint(path)


def test_checkpoint_cut_at_every_tenth_of_its_length(tmp_path):
    path = tmp_path / "latest.pt"
    save_checkpoint(path, {"step": 3, "weights": torch.rand(2000)})
    whole = path.read_bytes()
    for tenth in range(10):
        path.write_bytes(whole[: len(whole) * tenth // 10])
        with pytest.raises(CheckpointError, match="latest.pt cannot be read"):
            load_checkpoint(path)


# ------------------------------------------------------------- loaders, issue 33
def test_layout_flag_on_a_folder_of_another_layout_names_both(data):
    """Not the hdr-gs reader's own "run COLMAP": the folder is fine, the flag is wrong."""
    with pytest.raises(
        DatasetError,
        match=rf"{data} looks like layout hdr-nerf-synthetic, not hdr-gs: pass --layout hdr-nerf-synthetic "
        r"\(or leave --layout out\)",
    ):
        load_scene(DataConfig(data=data, layout="hdr-gs"))


def test_wrong_size_hdr_exr_is_named_not_the_photo(data):
    from mono_hdr_plugin.data.io import write_exr

    write_exr(data / "train_hdr" / "hdr_001.exr", np.ones((8, 8, 3), np.float32))
    with pytest.raises(DatasetError) as error:
        load_scene(DataConfig(data=data))
    message = str(error.value)
    assert message.startswith(str(data / "train_hdr" / "hdr_001.exr")), message
    assert "is 8x8 but the photos of view ./train/r_1 are 16x16" in message and ".png" not in message


def test_frame_listed_twice_names_file_and_frame(data):
    edit_json(data / "transforms_train.json", lambda t: t["frames"].append(t["frames"][0]))
    with pytest.raises(
        DatasetError,
        match=r"transforms_train.json: frames\[3\].file_path './train/r_0' is listed twice \(also frames\[0\]\)",
    ):
        load_scene(DataConfig(data=data))


@pytest.fixture
def gs_data(tmp_path):
    folder = tmp_path / "gs"
    write_disk_scene(folder, layout="hdr-gs")
    return folder


def test_two_colmap_entries_of_one_view_are_refused(gs_data):
    """A second image entry 000_1.png takes the same <view>_<e> photos as 000_0.png."""
    import pycolmap

    model = pycolmap.Reconstruction(str(gs_data / "sparse" / "0"))
    first = model.images[1]
    model.add_image_with_trivial_frame(
        pycolmap.Image(name="000_1.png", camera_id=1, image_id=99), first.cam_from_world()
    )
    model.write(str(gs_data / "sparse" / "0"))
    with pytest.raises(DatasetError, match=r"sparse/0: images 000_0.png and 000_1.png both take the photo 000_0.png"):
        load_scene(DataConfig(data=gs_data))


def test_exposure_entry_of_no_photo_is_refused_in_hdr_gs(gs_data):
    """As the HDR-NeRF synthetic reader refuses an entry that matches no frame."""
    edit_json(gs_data / "exposures.json", lambda table: table.update({"042_0.png": 2.0}))
    with pytest.raises(DatasetError, match=r"exposures.json: entries \['042_0.png'\] match no photo of .*sparse/0"):
        load_scene(DataConfig(data=gs_data))


def test_splits_holding_out_every_view_names_the_file(gs_data):
    names = sorted(json.loads((gs_data / "exposures.json").read_text()))
    (gs_data / "splits.json").write_text(json.dumps({"test": [n for n in names if n.endswith("_0.png")]}))
    with pytest.raises(DatasetError, match=r"splits.json: holds out every image of sparse/0 for testing"):
        load_scene(DataConfig(data=gs_data))
