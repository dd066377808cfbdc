"""`mono-hdr view` and `mono-hdr train --viewer` as a person uses them: a real server, a real
headless Chromium, a screenshot, and a clean stop on Ctrl+C."""

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest
from browser_screenshot import chromium_available, screenshot_when  # examples/, on sys.path via conftest

from mono_hdr_plugin.apps.cli import main

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not chromium_available() and not os.environ.get("CI"),
        reason="needs Debian's chromium and chromium-driver (.ci/run installs them)",
    ),
]
SCENE_WIDTH = 800  # the left part of the 1200-px window shows the render; the controls sit on the right


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_for_page(url: str, process: subprocess.Popen, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"the viewer exited with {process.returncode}: {process.stderr.read()}")
        try:
            urllib.request.urlopen(url, timeout=2).read()
            return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"no page at {url} after {timeout} s")


def rendered(pixels: np.ndarray) -> bool:
    """The scene area shows an image: many distinct colours, not the empty dark canvas."""
    scene = pixels[100:-60, 60:SCENE_WIDTH].reshape(-1, 3)
    return scene.std(axis=0).mean() > 8.0 and len(np.unique(scene // 8, axis=0)) > 50


def stop(process: subprocess.Popen, url: str) -> str:
    """Ctrl+C: the process exits 0 within seconds and the port is closed."""
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 0, stderr
    with pytest.raises(OSError):
        urllib.request.urlopen(url, timeout=2)
    return stderr


@pytest.fixture(scope="module")
def gs_checkpoint(tmp_path_factory):
    out = tmp_path_factory.mktemp("view") / "run"
    main(
        [
            "train",
            "gs",
            "--scene",
            "demo",
            "--max-steps",
            "60",
            "--out",
            str(out),
            "--quiet",
            "--max-eval-views",
            "1",
            "--no-save-renders",
            "--backbone.random-init-points",
            "3000",
        ]
    )
    return out / "checkpoints" / "latest.pt"


def test_view_serves_a_rendered_page_and_stops_cleanly(gs_checkpoint, tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mono_hdr_plugin.apps.cli",
            "view",
            "--checkpoint",
            str(gs_checkpoint),
            "--port",
            str(port),
            "--out",
            str(tmp_path / "saved"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for_page(url, process)
        pixels = screenshot_when(url, tmp_path / "viewer.png", rendered)
    finally:
        if process.poll() is None:
            stderr = stop(process, url)
    assert rendered(pixels), f"the screenshot {tmp_path / 'viewer.png'} shows no render"
    assert "render failed" not in stderr and "viewer stopped" in stderr


def test_train_with_viewer_shows_training_and_stops_cleanly(tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mono_hdr_plugin.apps.cli",
            "train",
            "gs",
            "--scene",
            "demo",
            "--max-steps",
            "40",
            "--out",
            str(tmp_path / "run"),
            "--quiet",
            "--max-eval-views",
            "1",
            "--no-save-renders",
            "--backbone.random-init-points",
            "3000",
            "--viewer",
            "--viewer-port",
            str(port),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        wait_for_page(url, process)
        pixels = screenshot_when(url, tmp_path / "training.png", rendered)
        assert rendered(pixels), f"the screenshot {tmp_path / 'training.png'} shows no render"
        deadline = time.monotonic() + 300
        while not (tmp_path / "run" / "metrics.json").exists() and time.monotonic() < deadline:
            time.sleep(1)  # training goes on to the end while the page is open
        assert (tmp_path / "run" / "metrics.json").exists()
    finally:
        if process.poll() is None:
            stderr = stop(process, url)
    assert "training done" in stderr and "render failed" not in stderr
