"""Crash safety: a training run killed with SIGKILL at a random moment leaves its last checkpoint
loadable under the real name, and `--resume` continues from it. Checkpoints are written to a
temporary file and renamed (docs/robustness.md), so a half-written file never has the name; the
next run removes the temporary files and takes over the dead run's claim on --out."""

import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from cli_driver import environment, train_args, write_driver

from mono_hdr_plugin.training import checkpoints
from mono_hdr_plugin.training.checkpoints import load_checkpoint, save_checkpoint

MAX_STEPS = 100_000  # never reached: every run but the last is killed


def train_command(driver: Path, data: Path, out: Path, max_steps: int, resume: bool) -> list[str]:
    return [
        sys.executable,
        str(driver),
        *train_args(data, out, max_steps, "--checkpoint-every", "1", *(["--resume"] if resume else [])),
    ]


def checkpoint_files(out: Path) -> list[str]:
    folder = out / "checkpoints"
    return sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []


def kill_at_random_moments(tmp_path: Path, data: Path, kills: int, seed: int) -> None:
    rng = random.Random(seed)
    driver = write_driver(tmp_path)
    out = tmp_path / "run"
    latest = out / "checkpoints" / "latest.pt"
    last_step, seen_mtime = 0, 0
    for kill in range(kills):
        process = subprocess.Popen(
            train_command(driver, data, out, MAX_STEPS, resume=kill > 0),
            env=environment(),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        deadline = time.monotonic() + 120
        # wait until this run has written a checkpoint of its own, then kill at a random moment
        while time.monotonic() < deadline and process.poll() is None:
            if latest.is_file() and latest.stat().st_mtime_ns > seen_mtime:
                break
            time.sleep(0.05)
        assert process.poll() is None, f"run {kill} ended early: {process.stderr.read().decode()[-2000:]}"
        time.sleep(rng.uniform(0.0, 0.8))
        process.send_signal(signal.SIGKILL)
        process.wait()
        process.stderr.close()
        seen_mtime = latest.stat().st_mtime_ns
        context = f"kill {kill} (seed {seed})"
        leftovers = [name for name in checkpoint_files(out) if name != "latest.pt"]
        assert all(name.startswith(".latest.tmp-") for name in leftovers), f"{context}: {leftovers}"
        payload = load_checkpoint(latest)  # raises CheckpointError if half-written
        assert payload["step"] >= max(last_step, 1), f"{context}: step went from {last_step} to {payload['step']}"
        tensors = [t for t in payload["pipeline"].values() if isinstance(t, torch.Tensor)]  # not the extra state
        assert all(torch.isfinite(t).all() for t in tensors), context
        last_step = payload["step"]
    # the final run resumes from the last checkpoint and finishes
    finish = last_step + 3
    result = subprocess.run(
        train_command(driver, data, out, finish, resume=True),
        env=environment(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"at step {last_step}" in result.stderr
    assert "which is no longer running; taking it over" in result.stderr  # the killed run's claim on --out
    assert load_checkpoint(latest)["step"] == finish
    assert checkpoint_files(out) == ["latest.pt"]  # temporary files of killed writes removed at the next start
    assert '"steps": ' + str(finish) in (out / "metrics.json").read_text()


def test_sigkill_at_random_moments_then_resume(tmp_path, disk_scene):
    kill_at_random_moments(tmp_path, disk_scene, kills=2, seed=8)


@pytest.mark.slow
def test_sigkill_many_times_then_resume(tmp_path, disk_scene):
    kill_at_random_moments(tmp_path, disk_scene, kills=12, seed=int.from_bytes(os.urandom(2), "little"))


def test_crash_inside_torch_save_keeps_previous_checkpoint(tmp_path, monkeypatch):
    """In-process twin of the SIGKILL test at the worst moment: half the bytes are written."""
    path = tmp_path / "checkpoints" / "latest.pt"
    save_checkpoint(path, {"step": 7, "weights": torch.arange(1000.0)})

    def crashing_save(payload, handle):
        handle.write(b"PK\x03\x04 half a zip file")
        raise KeyboardInterrupt("killed while saving")

    monkeypatch.setattr(checkpoints.torch, "save", crashing_save)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(path, {"step": 8, "weights": torch.zeros(1000)})
    monkeypatch.undo()
    payload = load_checkpoint(path)
    assert payload["step"] == 7 and torch.equal(payload["weights"], torch.arange(1000.0))
    assert checkpoint_files(tmp_path) == ["latest.pt"]  # the temporary file was removed
