"""An output folder is a run (docs/robustness.md, "Output folders"): one writer at a time, an
earlier run is never replaced unasked, --resume continues only the same model on the same data,
and --overwrite never removes anything outside the folder it owns or holding the inputs."""

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time

import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
from cli_driver import environment, train_args, write_driver
from hard_scenes import write_disk_scene

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.data.outputs import RUN_FILE, OutputError, check_output, claim_output
from mono_hdr_plugin.training.checkpoints import load_checkpoint
from mono_hdr_plugin.training.config import TRAIN_OUTPUTS
from mono_hdr_plugin.training.resume import ResumeMismatch


@pytest.fixture
def data(tmp_path, disk_scene):
    folder = tmp_path / "scene"
    shutil.copytree(disk_scene, folder)
    return folder


@pytest.fixture(scope="module")
def trained(tmp_path_factory, disk_scene):
    """A finished 2-step run (checkpoint, metrics.json, renders/), copied by each test that changes it."""
    out = tmp_path_factory.mktemp("trained") / "run"
    main(train_args(disk_scene, out, 2, "--save-renders"))
    return out


@pytest.fixture
def run(tmp_path, trained):
    out = tmp_path / "run"
    shutil.copytree(trained, out)
    return out


def snapshot(folder) -> dict[str, bytes]:
    """Every file below `folder` with its bytes (the claim file's state changes; it is left out)."""
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and p.name != RUN_FILE
    }


def dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


# ------------------------------------------------------------------ an earlier run in --out
def test_training_again_into_a_finished_run_is_refused_and_keeps_it(run, disk_scene):
    before = snapshot(run)
    with pytest.raises(
        OutputError,
        match=r"holds the output of an earlier `mono-hdr train` \(checkpoints/, "
        r"renders/, metrics.json\); pass --resume to continue it, pass --overwrite",
    ):
        main(train_args(disk_scene, run, 3))
    assert snapshot(run) == before


def test_resume_continues_and_overwrite_replaces(run, disk_scene):
    main(train_args(disk_scene, run, 4, "--resume"))
    assert load_checkpoint(run / "checkpoints" / "latest.pt")["step"] == 4
    (run / "renders" / "stale.png").write_bytes(b"from the earlier run")
    main(train_args(disk_scene, run, 1, "--overwrite"))
    assert load_checkpoint(run / "checkpoints" / "latest.pt")["step"] == 1
    assert not (run / "renders").exists()  # the earlier run's renders went with it (this run saves none)
    assert json.loads((run / "metrics.json").read_text())["steps"] == 1


def test_resume_and_overwrite_together_are_refused(tmp_path, disk_scene):
    with pytest.raises(ValueError, match="--resume continues the run in --out and --overwrite replaces it"):
        main(train_args(disk_scene, tmp_path / "run", 1, "--resume", "--overwrite"))


def test_overwrite_fails_on_bad_data_before_removing_anything(run, tmp_path):
    """The earlier run goes only once the new one is ready to write: a bad --data keeps it."""
    before = snapshot(run)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        main(train_args(tmp_path / "nowhere", run, 1, "--overwrite"))
    assert snapshot(run) == before


def test_foreign_files_are_never_removed(tmp_path, disk_scene):
    """A folder mono-hdr did not write (no claim file) is not replaced, even with --overwrite."""
    out = tmp_path / "mine"
    (out / "renders").mkdir(parents=True)
    (out / "renders" / "holiday.jpg").write_bytes(b"a photo")
    (out / "metrics.json").write_text("{}")
    before = snapshot(out)
    for flags in ((), ("--overwrite",)):
        with pytest.raises(OutputError, match=r"holds renders/, metrics.json, which mono-hdr did not write"):
            main(train_args(disk_scene, out, 1, *flags))
    assert snapshot(out) == before


def test_overwrite_never_removes_the_inputs(run, tmp_path):
    """--data inside a folder --overwrite would remove: refused, nothing removed."""
    data = run / "renders" / "scene"
    write_disk_scene(data)
    before = snapshot(run)
    with pytest.raises(
        OutputError,
        match=r"--overwrite would remove .*renders, which holds the input .*scene; "
        "nothing was removed",
    ):
        main(train_args(data, run, 1, "--overwrite"))
    assert snapshot(run) == before


def test_overwrite_removes_a_link_not_what_it_points_to(run, tmp_path, disk_scene):
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("not the run's")
    shutil.rmtree(run / "renders")
    (run / "renders").symlink_to(elsewhere, target_is_directory=True)
    main(train_args(disk_scene, run, 1, "--overwrite"))
    assert (elsewhere / "keep.txt").read_text() == "not the run's"
    assert not (run / "renders").exists()


def test_out_that_is_a_file_is_one_clear_error_before_loading(tmp_path, disk_scene, monkeypatch):
    import mono_hdr_plugin.data.loading as loading

    monkeypatch.setattr(loading, "load_scene", lambda config: pytest.fail("the data was loaded first"))
    (tmp_path / "out").write_text("")
    with pytest.raises(OutputError, match=r"--out .*out is a file, not a folder"):
        main(train_args(disk_scene, tmp_path / "out", 1))


# ------------------------------------------------------------------ one writer at a time
def test_second_run_is_refused_naming_the_first_ones_pid_and_host(tmp_path, disk_scene):
    out = tmp_path / "run"
    with (
        claim_output(out, "train", TRAIN_OUTPUTS),
        pytest.raises(
            OutputError,
            match=rf"is being written by `mono-hdr train` \(PID {os.getpid()} on host "
            rf"{socket.gethostname()} since .*\); wait for it to finish",
        ),
    ):
        main(train_args(disk_scene, out, 1))
    main(train_args(disk_scene, out, 1))  # released: the folder is free again
    assert json.loads((out / RUN_FILE).read_text())["state"] == "finished"


def test_two_trainings_started_together_one_refused_the_other_kept(tmp_path, disk_scene):
    """The issue's case with two real processes: the second exits 2 naming the first, whose results stay."""
    driver = write_driver(tmp_path)
    out = tmp_path / "run"
    first = subprocess.Popen(
        [sys.executable, str(driver), *train_args(disk_scene, out, 100_000)],
        env=environment(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while not ((out / RUN_FILE).is_file() and '"running"' in (out / RUN_FILE).read_text()):
            assert first.poll() is None and time.monotonic() < deadline, first.stderr.read()
            time.sleep(0.05)
        second = subprocess.run(
            [sys.executable, str(driver), *train_args(disk_scene, out, 1, "--overwrite")],
            env=environment(),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert second.returncode == 2
        assert f"is being written by `mono-hdr train` (PID {first.pid} on host {socket.gethostname()}" in second.stderr
        assert len(second.stderr.strip().splitlines()) == 1
        assert first.poll() is None  # the first run goes on
    finally:
        first.kill()
        first.wait()
        first.stderr.close()


def test_stale_claim_of_a_dead_process_is_taken_over_with_a_note(tmp_path, disk_scene, capsys):
    out = tmp_path / "run"
    out.mkdir()
    pid = dead_pid()
    (out / RUN_FILE).write_text(
        json.dumps(
            {"command": "train", "pid": pid, "host": socket.gethostname(), "started": time.time(), "state": "running"}
        )
    )
    main(train_args(disk_scene, out, 1))
    assert f"left claimed by `mono-hdr train` (PID {pid} on host {socket.gethostname()}" in capsys.readouterr().err
    assert load_checkpoint(out / "checkpoints" / "latest.pt")["step"] == 1


def test_claim_from_another_host_is_refused_naming_it(tmp_path, disk_scene):
    out = tmp_path / "run"
    out.mkdir()
    (out / RUN_FILE).write_text(
        json.dumps(
            {"command": "train", "pid": 4242, "host": "render-farm-7", "started": time.time(), "state": "running"}
        )
    )
    with pytest.raises(
        OutputError,
        match=r"claimed by `mono-hdr train` \(PID 4242 on host render-farm-7.*another "
        rf"machine.*delete .*{RUN_FILE}",
    ):
        main(train_args(disk_scene, out, 1))


def test_temporary_files_of_an_interrupted_write_are_removed_at_the_next_start(run, disk_scene, capsys):
    leftovers = [run / "checkpoints" / f".latest.tmp-{dead_pid()}.pt", run / f".metrics.tmp-{dead_pid()}.json"]
    for path in leftovers:
        path.write_bytes(b"half a file")
    in_use = run / "checkpoints" / f".latest.tmp-{os.getppid()}.pt"  # its writer (our parent) still runs
    in_use.write_bytes(b"being written")
    main(train_args(disk_scene, run, 3, "--resume"))
    assert not any(path.exists() for path in leftovers) and in_use.exists()
    assert "removed 2 temporary file(s) an interrupted write left" in capsys.readouterr().err


# ------------------------------------------------------------------ --resume checks what it continues
def test_resume_on_other_data_is_refused_and_keeps_the_checkpoint(run, tmp_path):
    other = tmp_path / "other"
    write_disk_scene(other, views=4)
    before = snapshot(run)
    with pytest.raises(
        ResumeMismatch,
        match=r"cannot resume from .*latest.pt: it was trained on scene 'scene' "
        r"\(.*scene, 3 training views\), not on scene 'other' \(.*other, 2 "
        r"training views\); changed: --data .*other \(was .*scene\)",
    ):
        main(train_args(other, run, 5, "--resume"))
    assert snapshot(run) == before


def test_resume_on_a_moved_copy_of_the_same_data_continues(run, disk_scene, tmp_path):
    moved = tmp_path / "moved"
    shutil.copytree(disk_scene, moved)
    main(train_args(moved, run, 3, "--resume"))
    assert load_checkpoint(run / "checkpoints" / "latest.pt")["step"] == 3


@pytest.mark.parametrize(
    "flags,message",
    [
        (("--method", "hdr-gs"), "it was trained with --method mono, not hdr-gs"),
        (("--hidden", "64"), "it was trained with --hidden 128, not 64"),
        (("--exposure-index", "2"), "it was trained on scene 'scene'.*changed: --exposure-index 2 \\(was 1\\)"),
    ],
)
def test_resume_with_another_model_or_data_is_one_line(run, disk_scene, flags, message, monkeypatch, capsys):
    from mono_hdr_plugin.apps import cli

    before = snapshot(run)
    monkeypatch.setattr("sys.argv", ["mono-hdr", *train_args(disk_scene, run, 5, "--resume", *flags)])
    monkeypatch.delenv("MONO_HDR_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        cli.run()
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err and "state_dict" not in err
    assert re.search(message, err), err
    assert snapshot(run) == before


def test_resume_with_a_changed_model_size_names_the_settings(run, disk_scene):
    with pytest.raises(
        ResumeMismatch,
        match=r"its model does not fit the one these flags build \(changed: "
        r"--backbone.resolution 12 \(was 20\)\)",
    ):
        main(train_args(disk_scene, run, 5, "--resume", "--backbone.resolution", "12"))


def test_resume_with_a_changed_learning_rate_continues_and_says_so(run, disk_scene, capsys):
    main(train_args(disk_scene, run, 3, "--resume", "--backbone.lr", "0.05"))
    assert "resuming with changed settings: --backbone.lr 0.05 (was 0.1)" in capsys.readouterr().err
    assert load_checkpoint(run / "checkpoints" / "latest.pt")["step"] == 3


# ------------------------------------------------------------------ eval, render, synth, process-data
def test_eval_into_the_training_folder_keeps_its_checkpoint(run):
    checkpoint = run / "checkpoints" / "latest.pt"
    before = checkpoint.read_bytes()
    with pytest.raises(
        OutputError,
        match=r"holds the output of an earlier `mono-hdr train` \(metrics.json, "
        r"renders/\); pass --overwrite",
    ):
        main(["eval", "--checkpoint", str(checkpoint), "--out", str(run)])
    main(["eval", "--checkpoint", str(checkpoint), "--out", str(run), "--overwrite", "--no-save-renders"])
    assert checkpoint.read_bytes() == before and not (run / "renders").exists()
    assert json.loads((run / "metrics.json").read_text())["steps"] == 2


def test_render_adds_to_its_own_folder_and_never_writes_into_another(run, tmp_path):
    checkpoint = run / "checkpoints" / "latest.pt"
    out = tmp_path / "render"
    main(["render", "--checkpoint", str(checkpoint), "--out", str(out), "--max-views", "1"])
    rendered = sorted(p.name for p in out.iterdir() if p.name != RUN_FILE)
    assert rendered and all(name.endswith((".exr", ".png")) for name in rendered)
    main(["render", "--checkpoint", str(checkpoint), "--out", str(out), "--max-views", "1", "--exposures", "8"])
    assert set(rendered) < {p.name for p in out.iterdir()}  # renders add up in their folder
    before = snapshot(run)
    with pytest.raises(
        OutputError, match="holds the output of `mono-hdr train`; `mono-hdr render` writes into a folder of its own"
    ):
        main(["render", "--checkpoint", str(checkpoint), "--out", str(run)])
    assert snapshot(run) == before


def test_synth_replaces_its_own_dataset_without_leaving_the_old_layout(tmp_path, tiny_demo, monkeypatch):
    from mono_hdr_plugin.apps.studio import dataset as studio_dataset
    from mono_hdr_plugin.data.layouts import detect_layout

    monkeypatch.setattr(studio_dataset, "get_scene", lambda name, resolution=None: tiny_demo)
    out = tmp_path / "synth"
    main(["synth", "--out", str(out), "--layout", "hdr-gs"])
    with pytest.raises(OutputError, match="earlier `mono-hdr synth`.*pass --overwrite"):
        main(["synth", "--out", str(out), "--layout", "hdr-nerf-synthetic"])
    main(["synth", "--out", str(out), "--layout", "hdr-nerf-synthetic", "--overwrite"])
    assert not (out / "sparse").exists() and detect_layout(out) == "hdr-nerf-synthetic"
    foreign = tmp_path / "photos"
    foreign.mkdir()
    (foreign / "IMG_1.jpg").write_bytes(b"a photo")
    with pytest.raises(OutputError, match="which mono-hdr did not write"):
        main(["synth", "--out", str(foreign), "--overwrite"])
    assert (foreign / "IMG_1.jpg").read_bytes() == b"a photo"


def test_process_data_overwrite_of_the_folder_holding_the_photos_is_refused(tmp_path):
    """The issue's case: --out PARENT --overwrite, PARENT holding --images (and an unrelated file)."""
    from PIL import Image

    from mono_hdr_plugin.apps.process_data import ProcessDataConfig, process_data

    photos = tmp_path / "parent" / "photos"
    photos.mkdir(parents=True)
    for index in range(3):
        Image.new("RGB", (8, 8), (index * 40, 0, 0)).save(photos / f"IMG_{index}.jpg")
    (tmp_path / "parent" / "notes.txt").write_text("unrelated")
    before = snapshot(tmp_path / "parent")
    with pytest.raises(
        OutputError,
        match=r"process-data --overwrite replaces .*parent, which holds the input "
        r".*photos; nothing was removed",
    ):
        process_data(ProcessDataConfig(images=photos, out=tmp_path / "parent", overwrite=True))
    assert snapshot(tmp_path / "parent") == before
    other = tmp_path / "not-a-dataset"
    other.mkdir()
    (other / "thesis.tex").write_text("years of work")
    with pytest.raises(OutputError, match="which this command did not write \\(it has no process_data.json\\)"):
        process_data(ProcessDataConfig(images=photos, out=other, overwrite=True))
    assert (other / "thesis.tex").read_text() == "years of work"


def test_check_output_creates_nothing_and_a_refused_claim_leaves_no_trace(tmp_path, disk_scene):
    out = tmp_path / "new"
    check_output(out, "train", TRAIN_OUTPUTS)
    assert not out.exists()
    with pytest.raises(FileNotFoundError):
        main(train_args(tmp_path / "missing-data", out, 1))
    assert not out.exists()  # created for the run, which wrote nothing: removed again
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "a.txt").write_text("a")
    with pytest.raises(OutputError):
        main(["render", "--checkpoint", str(tmp_path / "x.pt"), "--out", str(foreign)])
    assert [p.name for p in foreign.iterdir()] == ["a.txt"]
