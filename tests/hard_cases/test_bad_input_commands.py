"""Bad input to the commands (issue 33): each ends in one line naming the flag, file or key and the
fix, or in an acceptance that says what it did. Loader cases are in test_bad_input_matrix.py;
docs/robustness.md lists every case with its test."""

import json
import shutil
from pathlib import Path

import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
from cli_driver import run_cli, train_args, write_driver
from hard_scenes import make_scene, make_trainer
from helpers import FakeClock

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.training.checkpoints import CheckpointError


# ---------------------------------------------------------------------------- render
@pytest.mark.parametrize(
    "extra,message",
    [
        (["--path", "spiral", "--video", "out.txt"], r"--video must name a \.mp4, \.mkv, \.mov file .*out\.txt"),
        (["--sweep", "--strip", "strip.jpg"], r"--strip must name a \.png file, got strip\.jpg"),
        (["--video", "a.mp4"], r"--video applies to --path renders and --sweep renders only, not to test-view"),
        (["--path", "spiral", "--exposures", "2"], r"--exposures applies to test-view renders .* not to --path"),
        (["--sweep", "--ev", "1"], r"--ev applies to --path renders only, not to --sweep renders"),
        (["--path", "dataset", "--sweep"], "--path and --sweep are two different renders"),
    ],
)
def test_render_flags_are_refused_before_loading_or_claiming(tmp_path, extra, message):
    """The checkpoint does not exist: the flag is named first, and --out is not created."""
    out = tmp_path / "render"
    with pytest.raises(FlagError, match=message):
        main(["render", "--checkpoint", str(tmp_path / "not-loaded.pt"), "--out", str(out), *extra])
    assert not out.exists()


def test_render_exr_frames_onto_a_file_is_refused(tmp_path):
    (tmp_path / "frames").write_text("")
    with pytest.raises(FlagError, match="--exr-frames must name a folder"):
        main(
            [
                "render",
                "--checkpoint",
                str(tmp_path / "x.pt"),
                "--path",
                "spiral",
                "--exr-frames",
                str(tmp_path / "frames"),
            ]
        )


# ---------------------------------------------------------------------------- warnings
def test_warning_reaches_the_user_as_one_plain_line(tmp_path, disk_scene):
    """Through the console entry point: `warning: <message>` on one line, not Python's
    `path/loading.py:114: UserWarning: ...` followed by a line of source code."""
    data = tmp_path / "scene"
    shutil.copytree(disk_scene, data)
    (data / "train_hdr" / "hdr_000.exr").unlink()
    result = run_cli(write_driver(tmp_path), train_args(data, tmp_path / "run", 1), timeout=300)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if "no HDR ground truth" in line]
    assert len(lines) == 1 and lines[0].startswith("warning: scene 'scene'"), result.stderr
    assert "1 of 6 views have no HDR ground truth" in lines[0] and lines[0].endswith("meant to have them.")
    assert "UserWarning" not in result.stderr and "warnings.warn(" not in result.stderr


# ---------------------------------------------------------------------------- train --resume
@pytest.fixture
def data(tmp_path, disk_scene):
    """A private copy of the on-disk scene."""
    folder = tmp_path / "scene"
    shutil.copytree(disk_scene, folder)
    return folder


def test_resume_without_a_run_says_drop_resume_before_loading(tmp_path, monkeypatch):
    """train takes no .pt file: the fix is to drop --resume or point --out at the run."""
    import mono_hdr_plugin.data.loading as loading

    monkeypatch.setattr(loading, "load_scene", lambda config: pytest.fail("the scene was loaded first"))
    with pytest.raises(CheckpointError) as error:
        main(train_args(tmp_path / "unused", tmp_path / "fresh", 1, "--resume"))
    message = str(error.value)
    assert "drop --resume" in message and "point --out at the folder of the run" in message
    assert "fresh/checkpoints/latest.pt does not exist" in message and ".pt file" not in message
    assert not (tmp_path / "fresh").exists()


@pytest.fixture
def run_at_step_3(tmp_path, data):
    out = tmp_path / "run"
    main(train_args(data, out, 3))
    return out


def test_resume_beyond_max_steps_is_refused_and_keeps_the_run(run_at_step_3, data):
    checkpoint, metrics = run_at_step_3 / "checkpoints" / "latest.pt", run_at_step_3 / "metrics.json"
    before = checkpoint.read_bytes(), metrics.read_bytes()
    with pytest.raises(FlagError) as error:
        main(train_args(data, run_at_step_3, 2, "--resume"))
    assert f"the run in {run_at_step_3} is at step 3 > --max-steps 2: nothing to train" in str(error.value)
    assert "raise --max-steps" in str(error.value)
    assert (checkpoint.read_bytes(), metrics.read_bytes()) == before


def test_resume_at_max_steps_trains_nothing_says_so_and_keeps_the_checkpoint(run_at_step_3, data, capsys):
    checkpoint, metrics = run_at_step_3 / "checkpoints" / "latest.pt", run_at_step_3 / "metrics.json"
    before = checkpoint.read_bytes()
    metrics.unlink()  # as after a Ctrl-C during the final evaluation: resuming scores it
    main(train_args(data, run_at_step_3, 3, "--resume"))
    assert f"the run in {run_at_step_3} is at step 3 = --max-steps 3: nothing to train" in capsys.readouterr().err
    assert checkpoint.read_bytes() == before
    assert json.loads(metrics.read_text())["steps"] == 3


# ---------------------------------------------------------------------------- --max-seconds alone
@pytest.mark.parametrize(
    "max_steps,max_seconds,steps",
    [
        (None, 10.0, 20),  # the time budget alone: 20 steps of 0.5 s, past the default step count
        (None, None, 6),  # neither: the default step count
        (8, 10.0, 8),  # both: whichever comes first
    ],
)
def test_max_seconds_alone_is_not_cut_at_the_default_steps(tmp_path, monkeypatch, max_steps, max_seconds, steps):
    """The default step count is made 6 here, so the test is quick; a step takes 0.5 s of a fake clock."""
    import mono_hdr_plugin.training.config as config_module
    import mono_hdr_plugin.training.trainer as trainer_module

    monkeypatch.setattr(config_module, "DEFAULT_MAX_STEPS", 6)
    monkeypatch.setattr(trainer_module.time, "perf_counter", FakeClock(0.5).perf_counter)
    trainer = make_trainer(tmp_path, "voxel-grid", make_scene(size=8), max_steps=max_steps, max_seconds=max_seconds)
    trainer.fit()
    assert trainer.step == steps
    if max_steps is None and max_seconds is not None:  # the schedules were sized from the time, not the default
        assert trainer.run_length == trainer.backbone.max_steps == 20


def test_help_says_how_the_two_budgets_combine(capsys):
    with pytest.raises(SystemExit):
        main(["train", "voxel-grid", "--help"])
    text = " ".join(capsys.readouterr().out.replace("│", " ").split())
    assert "Optimiser steps (default 3000; with --max-seconds alone, as many as fit in that time)" in text
    assert "Without --max-steps the time alone ends the run. Schedules (learning-rate decay, densification)" in text


# ---------------------------------------------------------------------------- eval --data
def copy_without_frame(source, target, split: str):
    """A copy of the scene without the last frame of `split` (and its exposure entries)."""
    shutil.copytree(source, target)
    transforms = json.loads((target / f"transforms_{split}.json").read_text())
    dropped = transforms["frames"].pop()["file_path"]
    (target / f"transforms_{split}.json").write_text(json.dumps(transforms))
    exposures = json.loads((target / f"exposure_{split}.json").read_text())
    kept = {name: value for name, value in exposures.items() if not name.startswith(dropped + "_")}
    (target / f"exposure_{split}.json").write_text(json.dumps(kept))
    return target


def test_eval_on_other_data_says_what_the_model_was_trained_on(run_at_step_3, data, tmp_path):
    """A held-out copy (here: one test view fewer) is scored, with one line naming both scenes."""
    other = copy_without_frame(data, tmp_path / "held-out", "test")
    checkpoint = run_at_step_3 / "checkpoints" / "latest.pt"
    with pytest.warns(UserWarning) as caught:
        main(["eval", "--checkpoint", str(checkpoint), "--data", str(other), "--out", str(tmp_path / "e")])
    messages = [str(w.message) for w in caught if "was trained on" in str(w.message)]
    assert messages == [
        f"{checkpoint} was trained on scene 'scene' ({data}, 3 training views) and is scored on scene "
        f"'held-out' ({other}, 3 training views) (--data)"
    ]
    assert json.loads((tmp_path / "e" / "metrics.json").read_text())["steps"] == 3


def test_eval_on_its_own_data_says_nothing(run_at_step_3, data, tmp_path, recwarn):
    checkpoint = run_at_step_3 / "checkpoints" / "latest.pt"
    main(["eval", "--checkpoint", str(checkpoint), "--data", str(data), "--out", str(tmp_path / "e")])
    assert not [w for w in recwarn if "was trained on" in str(w.message)]


def test_eval_on_data_with_other_training_views_is_refused(run_at_step_3, data, tmp_path):
    other = copy_without_frame(data, tmp_path / "fewer", "train")
    with pytest.raises(
        FlagError,
        match=r"--data: .*latest.pt was trained on scene 'scene' \(.*3 training views\), "
        r"which does not fit scene 'fewer' \(.*2 training views\)",
    ):
        main(
            [
                "eval",
                "--checkpoint",
                str(run_at_step_3 / "checkpoints" / "latest.pt"),
                "--data",
                str(other),
                "--out",
                str(tmp_path / "e"),
            ]
        )
    assert not (tmp_path / "e").exists()


# ---------------------------------------------------------------------------- scenes
class RenderStarted(Exception):
    """Raised where Mitsuba would start rendering."""


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    """An empty render cache, and Mitsuba replaced by a stop: nothing renders for minutes."""
    import mono_hdr_plugin.apps.studio.render as studio_render

    def render_starts():
        raise RenderStarted

    monkeypatch.setenv("MONO_HDR_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(studio_render, "_mitsuba", render_starts)
    return tmp_path / "cache"


def test_scenes_on_a_fresh_machine_says_it_renders_before_rendering(fresh_cache, capsys):
    from mono_hdr_plugin.apps.studio.scenes import SCENES

    with pytest.raises(RenderStarted):
        main(["scenes"])
    notice, first, *rest = capsys.readouterr().err.splitlines()
    assert notice.startswith(f"{len(SCENES)} of {len(SCENES)} built-in scenes are not rendered yet")
    # demo's 35 views at 512 x 512 x 121 spp took 20.2 minutes; a guess grows with pixels, samples and
    # views (the tests' scenes are tiny), and says for which scenes it is one (none rendered here)
    seconds = sum(
        20.2 * 60 * scene.width * scene.height * scene.spp * len(scene.cameras()) / (512 * 512 * 121 * 35)
        for scene in SCENES.values()
    )
    assert round(seconds) < 60  # tiny scenes: the estimate reads in seconds
    expected = f"about {round(seconds)} s"
    guessed = ", ".join(SCENES)
    assert (
        f"{expected} (at demo's rate for {guessed}, never rendered here), once (cached in {fresh_cache / 'studio'})"
        in notice
    )
    assert "`mono-hdr scenes --no-render` lists them now" in notice
    scene = next(iter(SCENES.values()))
    assert first.startswith(f"rendering studio scene {scene.name} at {scene.width}x{scene.height} with Mitsuba (")
    assert f"cached in {fresh_cache / 'studio'} for next time" in first and not rest


def test_scenes_no_render_lists_at_once(fresh_cache, capsys):
    main(["scenes", "--no-render"])  # Mitsuba is never started
    captured = capsys.readouterr()
    assert "Built-in studio scenes" in captured.out and "demo" in captured.out and not captured.err


def test_synth_to_a_layout_it_cannot_write_is_refused_before_rendering(fresh_cache, tmp_path):
    """Mitsuba would stop the test with RenderStarted: the flag is named before minutes of rendering."""
    with pytest.raises(FlagError, match=r"--layout 'bogus' cannot be written; choose one of llff, hdr-gs, "):
        main(["synth", "--scene", "demo", "--layout", "bogus", "--out", str(tmp_path / "synth")])
    assert not (tmp_path / "synth").exists()


# ---------------------------------------------------------------------------- data flags
def test_data_and_scene_together_are_refused(tmp_path, data):
    """--data used to win silently over --scene."""
    with pytest.raises(FlagError, match=rf"--data {data} and --scene demo name two scenes: pass one of them"):
        main([*train_args(data, tmp_path / "run", 1), "--scene", "demo"])


# ---------------------------------------------------------------------------- first hour
def test_first_build_of_a_cpp_kernel_says_so_before_compiling(tmp_path, monkeypatch, capsys):
    """The compiler is silent for about 10 s: the notice comes first; a cached build says nothing."""
    import torch.utils.cpp_extension

    from mono_hdr_plugin.core.cpp_extensions import load_cpp_extension

    said_before_building = []

    def fake_build(name, build_directory, **options):
        said_before_building.append(capsys.readouterr().err)
        (Path(build_directory) / f"{name}.so").write_bytes(b"")
        return name

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    monkeypatch.setattr(torch.utils.cpp_extension, "load", fake_build)
    load_cpp_extension("probe", tmp_path / "probe.cpp")
    load_cpp_extension.cache_clear()  # as in a new process: the build on disk is found
    load_cpp_extension("probe", tmp_path / "probe.cpp")
    load_cpp_extension.cache_clear()
    first, second = said_before_building
    assert first.startswith(f"building the C++ kernel probe (first use, about 10 s; cached in {tmp_path / 'ext'}")
    assert second == ""
