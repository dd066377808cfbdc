"""Faults end in one line and keep what was there (docs/robustness.md, "Faults"): a full disk, a
read-only or file --out, Ctrl-C, SIGKILL in the middle of a checkpoint write, a diverging or
never-finite run, and checkpoints that are not ours."""

import errno
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import register_backbone  # noqa: F401 - registers "voxel-grid" (examples/, on sys.path via conftest)
import torch
from cli_driver import environment, run_cli, run_in_tmpfs, train_args, write_driver
from hard_scenes import make_scene, make_trainer

from mono_hdr_plugin.apps import cli
from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.data.outputs import OutputError
from mono_hdr_plugin.training import checkpoints
from mono_hdr_plugin.training.checkpoints import CheckpointError, load_checkpoint
from mono_hdr_plugin.training.trainer import Trainer, TrainingDiverged


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def run_console(argv, monkeypatch, capsys) -> tuple[int, str]:
    """`mono-hdr ARGV` through the console entry point: (exit code, stderr)."""
    monkeypatch.setattr("sys.argv", ["mono-hdr", *argv])
    monkeypatch.delenv("MONO_HDR_DEBUG", raising=False)
    with pytest.raises(SystemExit) as exit_info:
        cli.run()
    return exit_info.value.code, capsys.readouterr().err


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error:")]


def temporary_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".*.tmp-*"))


# ------------------------------------------------------------------ full disk while saving
def full_disk_after(calls: int, monkeypatch):
    """torch.save that writes half a checkpoint and fails as a full disk does, from call `calls` on."""
    real_save, count = torch.save, {"n": 0}

    def save(payload, handle):
        count["n"] += 1
        if count["n"] <= calls:
            return real_save(payload, handle)
        handle.write(b"PK\x03\x04 half a checkpoint")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(checkpoints.torch, "save", save)


def test_full_disk_while_saving_keeps_the_previous_checkpoint_and_says_so(tmp_path, scene, monkeypatch):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=6, checkpoint_every=2)
    full_disk_after(1, monkeypatch)
    with pytest.raises(CheckpointError) as error:
        trainer.train()
    message = str(error.value)
    assert message.startswith("cannot save the checkpoint of step 4: ") and "No space left on device" in message
    assert f"The last good checkpoint is {trainer.checkpoint_path()} (step 2); --resume continues it" in message
    monkeypatch.undo()
    assert load_checkpoint(trainer.checkpoint_path())["step"] == 2
    assert temporary_files(tmp_path) == []


def test_full_disk_before_any_checkpoint_says_none_was_written(tmp_path, scene, monkeypatch):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=3, checkpoint_every=2)
    full_disk_after(0, monkeypatch)
    with pytest.raises(CheckpointError, match="No checkpoint has been written yet") as error:
        trainer.train()
    assert "latest.pt (step" not in str(error.value)


def test_full_disk_on_a_real_tmpfs_keeps_the_previous_checkpoint(tmp_path, disk_scene):
    """A tmpfs too small for two checkpoints: the first is written, the second cannot be, the first stays."""
    driver = write_driver(tmp_path)
    sizing = run_cli(driver, train_args(disk_scene, tmp_path / "sizing", 1))
    assert sizing.returncode == 0, sizing.stderr
    size = (tmp_path / "sizing" / "checkpoints" / "latest.pt").stat().st_size
    mount, kept = tmp_path / "small-disk", tmp_path / "kept"
    result = run_in_tmpfs(
        mount,
        f"size={size * 3 // 2 // 1024}k",
        [
            [sys.executable, str(driver), *train_args(disk_scene, mount / "run", 5, "--checkpoint-every", "1")],
            ["cp", "-a", str(mount / "run"), str(kept)],
        ],
    )
    assert result.returncode == 2, result.stderr
    [line] = error_lines(result.stderr)
    assert re.fullmatch(
        r"error: cannot save the checkpoint of step 2: .*latest.pt: No space left on device; the "
        r"disk is full: .* The last good checkpoint is .*latest.pt \(step 1\); --resume continues it",
        line,
    ), line
    assert load_checkpoint(kept / "checkpoints" / "latest.pt")["step"] == 1
    assert temporary_files(kept) == []


# ------------------------------------------------------------------ --out not writable
def test_read_only_out_is_one_line_before_anything_is_loaded(tmp_path, disk_scene):
    driver = write_driver(tmp_path)
    mount = tmp_path / "read-only"
    result = run_in_tmpfs(mount, "ro", [[sys.executable, str(driver), *train_args(disk_scene, mount / "run", 5)]])
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"error: --out {mount / 'run'} cannot be written (Read-only file system); the file system is read-only: "
        "choose a location on a writable disk"
    ]


def test_unwritable_out_is_refused_before_the_data_is_loaded(tmp_path, disk_scene, monkeypatch):
    """File-system stub: creating the claim file is denied (as in a folder without write permission)."""
    import mono_hdr_plugin.data.loading as loading
    from mono_hdr_plugin.data.outputs import RUN_FILE

    real_open = os.open

    def denying_open(path, flags, *args):
        if Path(path).name == RUN_FILE:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, flags, *args)

    monkeypatch.setattr(loading, "load_scene", lambda config: pytest.fail("the data was loaded first"))
    monkeypatch.setattr(os, "open", denying_open)
    with pytest.raises(OutputError, match=r"--out .*run cannot be written \(Permission denied\); fix its permissions"):
        main(train_args(disk_scene, tmp_path / "run", 1))


def test_metrics_that_cannot_be_written_say_the_trained_model_is_saved(tmp_path, scene, monkeypatch):
    import mono_hdr_plugin.training.trainer as train_module

    def full(path, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=2)
    monkeypatch.setattr(train_module, "write_json", full)
    with pytest.raises(
        OutputError,
        match=r"metrics.json: No space left on device; .*Training finished and its "
        r"checkpoint .*latest.pt is saved: once fixed, score it with `mono-hdr eval",
    ):
        trainer.train()
    assert load_checkpoint(trainer.checkpoint_path())["step"] == 2


# ------------------------------------------------------------------ Ctrl-C and SIGKILL
def test_ctrl_c_saves_a_checkpoint_and_prints_the_exact_resume_command(tmp_path, disk_scene, monkeypatch, capsys):
    real_step = Trainer.train_step

    def step_then_ctrl_c(self):
        record = real_step(self)
        if self.step == 3:
            os.kill(os.getpid(), signal.SIGINT)
        return record

    monkeypatch.setattr(Trainer, "train_step", step_then_ctrl_c)
    argv = train_args(disk_scene, tmp_path / "run", 50, "--checkpoint-every", "1000")
    code, err = run_console(argv, monkeypatch, capsys)
    assert code == 130
    latest = tmp_path / "run" / "checkpoints" / "latest.pt"
    command = f"mono-hdr {shlex.join([*argv, '--resume'])}"
    assert (
        err.strip().splitlines()[-1] == f"interrupted at step 3; checkpoint saved to {latest}. Resume with: {command}"
    )
    assert load_checkpoint(latest)["step"] == 3
    monkeypatch.undo()
    main(shlex.split(command)[1:])
    assert load_checkpoint(latest)["step"] == 50


def test_ctrl_c_in_a_real_process(tmp_path, disk_scene):
    driver = write_driver(tmp_path)
    out = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, str(driver), *train_args(disk_scene, out, 100_000)],
        env=environment(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not (out / "checkpoints").exists() and time.monotonic() < deadline:  # the first save: training runs
        time.sleep(0.05)
    time.sleep(0.5)
    process.send_signal(signal.SIGINT)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    match = re.search(
        r"interrupted at step (\d+); checkpoint saved to (.*latest.pt)\. Resume with: (mono-hdr .*)$", err.strip()
    )
    assert match, err
    step = int(match.group(1))
    assert load_checkpoint(Path(match.group(2)))["step"] == step
    resume = shlex.split(match.group(3))[1:]
    resume[resume.index("--max-steps") + 1] = str(step + 2)
    finished = run_cli(driver, resume)
    assert finished.returncode == 0, finished.stderr
    assert f"at step {step}" in finished.stderr
    assert load_checkpoint(out / "checkpoints" / "latest.pt")["step"] == step + 2


SLOW_WRITER = """
import io
import time
import torch
real_save = torch.save

def slow_save(payload, handle):  # a big checkpoint on a slow disk: seconds between first and last byte
    buffer = io.BytesIO()
    real_save(payload, buffer)
    data = buffer.getvalue()
    for start in range(0, len(data), 2048):
        handle.write(data[start:start + 2048])
        handle.flush()
        time.sleep(0.02)

torch.save = slow_save
"""


def test_sigkill_in_the_middle_of_a_checkpoint_write_keeps_the_previous_one(tmp_path, disk_scene):
    driver = write_driver(tmp_path)
    slow_driver = tmp_path / "slow_driver.py"
    slow_driver.write_text(SLOW_WRITER + driver.read_text())
    out = tmp_path / "run"
    checkpoints_folder, latest = out / "checkpoints", out / "checkpoints" / "latest.pt"
    process = subprocess.Popen(
        [sys.executable, str(slow_driver), *train_args(disk_scene, out, 100_000, "--checkpoint-every", "1")],
        env=environment(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + 300
        # wait for a complete checkpoint and, after it, a next one half written
        while time.monotonic() < deadline:
            partial = (
                [p for p in checkpoints_folder.glob(".latest.tmp-*.pt") if p.stat().st_size > 4096]
                if latest.is_file()
                else []
            )
            if partial:
                break
            assert process.poll() is None, process.stderr.read().decode()[-2000:]
            time.sleep(0.01)
        process.send_signal(signal.SIGKILL)
        process.wait()
    finally:
        process.kill()
        process.stderr.close()
    assert partial and partial[0].exists(), "the kill did not land inside a checkpoint write"
    step = load_checkpoint(latest)["step"]  # the previous checkpoint, whole
    assert step >= 1
    resumed = run_cli(driver, train_args(disk_scene, out, step + 1, "--resume"))
    assert resumed.returncode == 0, resumed.stderr
    assert "removed 1 temporary file(s) an interrupted write left" in resumed.stderr
    assert temporary_files(out) == [] and load_checkpoint(latest)["step"] == step + 1


# ------------------------------------------------------------------ divergence and NaN
def test_nan_patience_never_names_a_checkpoint_that_was_not_written(tmp_path, scene, monkeypatch):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=10, nan_patience=2, checkpoint_every=1000)
    original = trainer.method.losses
    monkeypatch.setattr(trainer.method, "losses", lambda *a: {k: v * torch.nan for k, v in original(*a).items()})
    with pytest.raises(TrainingDiverged) as error:
        trainer.train()
    assert "No checkpoint has been written yet (--checkpoint-every 1000)" in str(error.value)
    assert "latest.pt" not in str(error.value) and not trainer.checkpoint_path().exists()


def test_a_run_with_no_finite_step_is_never_saved_or_scored(tmp_path, scene, monkeypatch):
    """Patience longer than the run: every step skipped; the untrained model must not be reported."""
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=5, nan_patience=100)
    original = trainer.method.losses
    monkeypatch.setattr(trainer.method, "losses", lambda *a: {k: v * torch.nan for k, v in original(*a).items()})
    with pytest.raises(
        TrainingDiverged, match="none of the 5 steps had a finite loss.*nothing was trained, saved or scored"
    ):
        trainer.train()
    assert not trainer.checkpoint_path().exists() and not (tmp_path / "run" / "metrics.json").exists()


def test_non_finite_parameters_never_replace_a_good_checkpoint(tmp_path, scene):
    trainer = make_trainer(tmp_path, "voxel-grid", scene, max_steps=2)
    trainer.train()
    good = trainer.checkpoint_path().read_bytes()
    trainer.config.max_steps = 4
    for group in trainer.optimizer.param_groups:  # what a NaN learning rate does (the flag itself is refused)
        group["base_lr"] = float("nan")
    with pytest.raises(
        TrainingDiverged,
        match=r"parameters .* became NaN or Inf by step \d and are not saved\. The "
        r"last good checkpoint is .*latest.pt \(step 2\)",
    ):
        trainer.train()
    assert trainer.checkpoint_path().read_bytes() == good


# ------------------------------------------------------------------ checkpoints that are not ours
@pytest.mark.parametrize("content", ["module", "text", "folder", "empty"])
def test_a_file_that_is_not_our_checkpoint_is_one_line_without_unsafe_advice(tmp_path, content, monkeypatch, capsys):
    path = tmp_path / "model.pt"
    if content == "module":
        torch.save(torch.nn.Linear(2, 2), path)  # a whole pickled model, as many projects save
    elif content == "text":
        path.write_text("not a checkpoint at all")
    elif content == "folder":
        path.mkdir()
    else:
        path.write_bytes(b"")
    code, err = run_console(["eval", "--checkpoint", str(path), "--out", str(tmp_path / "eval")], monkeypatch, capsys)
    assert code == 2
    [line] = err.strip().splitlines()
    assert line.startswith(f"error: checkpoint {path}" if content != "module" else f"error: {path}")
    assert "weights_only" not in err and "Traceback" not in err


def test_resume_of_a_checkpoint_that_is_not_ours_is_one_line(tmp_path, disk_scene, monkeypatch, capsys):
    latest = tmp_path / "run" / "checkpoints" / "latest.pt"
    latest.parent.mkdir(parents=True)
    torch.save({"model": torch.nn.Linear(2, 2)}, latest)
    code, err = run_console(train_args(disk_scene, tmp_path / "run", 2, "--resume"), monkeypatch, capsys)
    assert code == 2
    assert error_lines(err) == [
        f"error: {latest} is not a mono-hdr-3d checkpoint: it holds Python objects, not just "
        "tensors and numbers, and such files are never loaded (unpickling them can run code)"
    ]


# ------------------------------------------------------------------ file-system errors, one line each
def test_data_that_is_a_file_is_named_as_such(tmp_path, monkeypatch, capsys):
    (tmp_path / "scene.zip").write_bytes(b"PK")
    code, err = run_console(train_args(tmp_path / "scene.zip", tmp_path / "run", 1), monkeypatch, capsys)
    assert code == 2
    assert error_lines(err) == [
        f"error: {tmp_path / 'scene.zip'}: is a file, not a folder; pass --data the dataset folder that holds it"
    ]


def test_bare_file_system_errors_become_one_line_with_the_fix(monkeypatch, capsys):
    def fail(argv=None):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), "/mnt/card/out")

    monkeypatch.setattr(cli, "main", fail)
    code, err = run_console([], monkeypatch, capsys)
    assert code == 2
    assert err.strip() == (
        "error: /mnt/card/out: Read-only file system; the file system is read-only: choose a "
        "location on a writable disk"
    )


def test_messages_are_printed_as_they_are_never_as_markup(tmp_path, monkeypatch, capsys):
    data = tmp_path / "[bold]scene[/]"
    code, err = run_console(train_args(data, tmp_path / "run", 1), monkeypatch, capsys)
    assert code == 2 and f"{data}: file not found" in err


def test_an_unreadable_file_is_a_permission_problem_not_a_damaged_one(tmp_path, disk_scene, monkeypatch):
    """File-system stub (tests may run as root, whom permissions do not stop): opening one photo is denied."""
    import builtins
    import shutil

    from mono_hdr_plugin.data.config import DataConfig
    from mono_hdr_plugin.data.errors import DatasetError
    from mono_hdr_plugin.data.loading import load_scene

    data = tmp_path / "scene"
    shutil.copytree(disk_scene, data)
    denied, real_open = data / "train" / "r_0_1.png", builtins.open

    def guarded_open(file, *args, **kwargs):
        if isinstance(file, (str, Path)) and Path(file) == denied:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", guarded_open)
    with pytest.raises(DatasetError, match=r"r_0_1.png: cannot be opened \(Permission denied\); fix its permissions"):
        load_scene(DataConfig(data=data))


def test_names_that_look_like_markup_train_and_print_their_metrics(tmp_path, disk_scene, capsys):
    """Scene and folder names are data, not rich markup: a scene `[red]scene` lost its name in the
    table, and an --out path holding `[/x]` raised MarkupError once training had finished."""
    import shutil

    data = tmp_path / "[red]scene"
    shutil.copytree(disk_scene, data)
    out = tmp_path / "run[" / "x]"  # the path reads .../run[/x]/...
    main(train_args(data, out, 1))
    printed = capsys.readouterr().out
    assert "[red]scene (1 steps" in printed and f"metrics written to {out / 'metrics.json'}" in printed
