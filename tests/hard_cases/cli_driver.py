"""Run `mono-hdr` in a child process, as a user does: the console entry point (one-line errors, exit
codes), the example voxel-grid backbone registered, one thread; optionally inside a small tmpfs
(a full disk) or a read-only one, mounted in a private mount namespace (`unshare`)."""

import functools
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
DRIVER = f"""
import sys
sys.path.insert(0, {str(EXAMPLES)!r})
import register_backbone  # registers voxel-grid
from mono_hdr_plugin.apps.cli import run
run()
"""


def write_driver(folder: Path) -> Path:
    driver = folder / "driver.py"
    driver.write_text(DRIVER)
    return driver


def environment() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def train_args(data: Path, out: Path, max_steps: int, *extra: str) -> list[str]:
    """`mono-hdr train voxel-grid` on a dataset folder, small and quick."""
    return [
        "train",
        "voxel-grid",
        "--data",
        str(data),
        "--out",
        str(out),
        "--max-steps",
        str(max_steps),
        "--quiet",
        "--no-save-renders",
        "--max-eval-views",
        "1",
        "--backbone.resolution",
        "20",
        "--backbone.samples-per-ray",
        "8",
        *extra,
    ]


def run_cli(driver: Path, args: list[str], timeout: float = 300, **env: str) -> subprocess.CompletedProcess:
    """The command's exit status and output; `env` adds environment variables to the child's."""
    return subprocess.run(
        [sys.executable, str(driver), *args],
        env={**environment(), **env},
        capture_output=True,
        text=True,
        errors="backslashreplace",  # a path that is not UTF-8 comes back as the bytes it names
        timeout=timeout,
    )


@functools.cache
def can_mount_tmpfs() -> bool:
    """Whether this machine lets a process mount a tmpfs in its own user and mount namespace."""
    try:
        probe = subprocess.run(
            ["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"], capture_output=True, timeout=30
        )
    except (OSError, subprocess.SubprocessError):
        return False
    return probe.returncode == 0


def run_in_tmpfs(
    mount: Path, options: str, commands: list[list[str]], timeout: float = 600
) -> subprocess.CompletedProcess:
    """Mount a tmpfs with `options` (e.g. "size=900k" or "ro") at `mount`, visible only to this child,
    then run `commands` one after another (the exit status is the first command's). The tmpfs is
    gone when the child ends: copy out what the test must inspect."""
    if not can_mount_tmpfs():
        pytest.skip("cannot mount a tmpfs here (unshare -rm not permitted)")
    mount.mkdir(parents=True, exist_ok=True)
    first, *rest = (shlex.join(command) for command in commands)
    script = (
        f"mount -t tmpfs -o {shlex.quote(options)} tmpfs {shlex.quote(str(mount))} || exit 99; "
        f"{first}; status=$?; " + "".join(f"{command}; " for command in rest) + "exit $status"
    )
    return subprocess.run(
        ["unshare", "-rm", "sh", "-c", script], env=environment(), capture_output=True, text=True, timeout=timeout
    )
