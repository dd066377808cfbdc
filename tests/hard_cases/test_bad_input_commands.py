"""Bad input to the commands (issue 33): each ends in one line naming the flag, file or key and the
fix, or in an acceptance that says what it did. Loader cases are in test_bad_input_matrix.py;
docs/robustness.md lists every case with its test."""

import shutil

import pytest
from cli_driver import run_cli, train_args, write_driver

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.core.validation import FlagError


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
