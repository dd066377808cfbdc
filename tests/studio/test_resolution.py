"""Studio scenes at any size: `--resolution N` for scenes, synth, train --scene and the benchmarks."""

import math
import re
from dataclasses import replace

import numpy as np
import pytest
import torch

from mono_hdr_plugin.apps.bench.curves import BenchCurvesConfig, curve_specs
from mono_hdr_plugin.apps.bench.runs import RunSpec
from mono_hdr_plugin.apps.studio.commands import SynthConfig, list_scenes, synth
from mono_hdr_plugin.apps.studio.dataset import get_scene
from mono_hdr_plugin.apps.studio.render import (
    measured_view_seconds,
    record_view_seconds,
    render_cache_path,
    render_minutes,
    render_scene,
    render_time_text,
    render_times_path,
)
from mono_hdr_plugin.core import progress
from mono_hdr_plugin.core.validation import FlagError
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.loading import load_scene


def test_cameras_keep_their_field_of_view():
    small, large = get_scene("demo", 16), get_scene("demo", 48)
    point = torch.tensor([[0.1, 0.2, 0.3]])
    for a, b in zip(small.cameras(), large.cameras()):
        assert (b.width, b.height) == (48, 48) and b.fx == pytest.approx(3 * a.fx)
        assert 2 * math.degrees(math.atan(24 / b.fx)) == pytest.approx(small.rig.fov_deg)
        torch.testing.assert_close(b.project(point)[0], 3 * a.project(point)[0], atol=1e-4, rtol=0)
        torch.testing.assert_close(b.c2w, a.c2w)


def test_each_size_is_cached_apart():
    assert render_cache_path(get_scene("demo", 16)) != render_cache_path(get_scene("demo", 32))
    assert get_scene("demo") is get_scene("demo", None)


def builtin(name: str, size: int):
    """The real built-in scene (tests otherwise see tiny variants, tests/conftest.py) at a size."""
    from mono_hdr_plugin.apps.studio.scenes import BUILTIN_SCENES

    return replace(next(scene for scene in BUILTIN_SCENES if scene.name == name), resolution=(size, size))


class TestRenderTimeEstimate:
    @pytest.fixture(autouse=True)
    def own_cache(self, monkeypatch, tmp_path):
        monkeypatch.setenv("MONO_HDR_CACHE", str(tmp_path / "cache"))

    def test_a_scene_never_rendered_here_is_guessed_at_demos_rate_per_sample(self):
        assert len(builtin("demo", 128).cameras()) == 35
        demo = render_minutes(builtin("demo", 512))[0]
        assert demo == pytest.approx(20.2)  # measured alone on 2 cores
        assert render_minutes(builtin("demo", 256))[0] == pytest.approx(demo / 4)
        assert builtin("lamp-room", 512).spp == 289 and builtin("demo", 512).spp == 121
        assert render_minutes(builtin("lamp-room", 512))[0] == pytest.approx(demo * 289 / 121)
        assert "guess" in render_time_text(builtin("lamp-room", 128))

    def test_a_measured_render_sets_the_estimate_of_that_scene_at_every_size(self):
        record_view_seconds(builtin("lamp-room", 64), 10.0)
        assert measured_view_seconds(builtin("lamp-room", 128)) == pytest.approx(40.0)
        assert render_minutes(builtin("lamp-room", 128)) == (pytest.approx(40.0 * 35 / 60), True)
        assert "measured" in render_time_text(builtin("lamp-room", 512))
        assert measured_view_seconds(builtin("demo", 512)) is None
        assert render_minutes(builtin("demo", 512)) == (pytest.approx(20.2), False)

    def test_a_damaged_times_file_falls_back_to_the_guess(self):
        render_times_path().parent.mkdir(parents=True)
        render_times_path().write_text('{"lamp-room": ')
        assert measured_view_seconds(builtin("lamp-room", 128)) is None
        record_view_seconds(builtin("lamp-room", 128), 5.0)  # and is replaced by the next render
        assert measured_view_seconds(builtin("lamp-room", 128)) == pytest.approx(5.0)

    def test_a_render_records_its_time_and_says_how_long_is_left(self, capsys, monkeypatch, tiny_demo):
        monkeypatch.setattr(progress, "LOG_EVERY_SECONDS", 0.0)  # a log, not a terminal: a line a view
        scene = tiny_demo
        assert not render_cache_path(scene).is_file()  # this test's own cache
        render_scene(scene)
        lines = [line for line in capsys.readouterr().err.splitlines() if " views, " in line]
        assert re.fullmatch(r"demo: 2 of 10 views, about \d+ s left", lines[0])
        assert len(lines) == 8 and lines[-1].startswith("demo: 9 of 10 views")
        view_seconds = measured_view_seconds(scene)
        assert view_seconds is not None and 0 < view_seconds < 60
        assert "measured" in render_time_text(replace(scene, resolution=(48, 48)))


def test_train_scene_at_a_size():
    data = load_scene(DataConfig(scene="demo", resolution=16))
    view = data.train[0]
    assert view.image.shape == (16, 16, 3) and view.hdr.shape == (16, 16, 3)
    assert (view.camera.width, view.camera.height) == (16, 16)
    assert load_scene(DataConfig(scene="demo")).train[0].image.shape == (24, 24, 3)  # the (tiny) default


def test_resolution_is_for_scenes_only(tmp_path):
    with pytest.raises(FlagError, match="--resolution 16 sizes a --scene.*--downscale"):
        load_scene(DataConfig(data=tmp_path, resolution=16))


def test_synth_writes_the_size(tmp_path):
    out = synth(SynthConfig(scene="demo", out=tmp_path / "synth", resolution=16))
    data = load_scene(DataConfig(data=out))
    assert data.train[0].image.shape == (16, 16, 3)
    np.testing.assert_allclose(data.train[0].camera.fx, get_scene("demo", 16).cameras()[0].fx, rtol=1e-5)


def test_scenes_lists_the_size():
    rows = list_scenes(render=False, resolution=40)
    assert rows and all(row["resolution"] == "40x40" for row in rows)


def test_bench_specs_carry_the_size():
    specs = curve_specs(BenchCurvesConfig(backbones=("gs",), methods=("mono",), resolution=256))
    assert [spec.resolution for spec in specs] == [256]
    assert specs[0].key.endswith("|256px")
    assert RunSpec("gs").key == "gs|mono|None|demo|1|1:1|(True, True, True)|0|()"  # rows stored before keep theirs
