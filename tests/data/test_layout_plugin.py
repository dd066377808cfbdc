"""A dataset layout registered from outside the package (examples/register_layout.py) works everywhere."""

import json
import math

import pytest
import register_backbone
import register_layout  # noqa: F401 - registers "scene-json" (examples/, on sys.path via conftest)
import torch

from mono_hdr_plugin.apps.cli import main
from mono_hdr_plugin.apps.studio.dataset import studio_captured_scene
from mono_hdr_plugin.data.config import DataConfig
from mono_hdr_plugin.data.errors import DatasetError
from mono_hdr_plugin.data.layouts import LAYOUTS, detect_layout, writable_layouts, write_layout
from mono_hdr_plugin.data.loading import load_scene
from mono_hdr_plugin.training.config import train_config_for
from mono_hdr_plugin.training.trainer import Trainer


@pytest.fixture
def written(tmp_path, tiny_demo):
    folder = tmp_path / "scene"
    write_layout(studio_captured_scene(tiny_demo), folder, "scene-json")
    return folder


class TestRegistration:
    def test_registered_writable_and_listed(self, capsys):
        assert LAYOUTS.available()["scene-json"].source == "python: register_layout"
        assert "scene-json" in writable_layouts()
        main(["layouts"])
        out = capsys.readouterr().out
        assert "scene-json" in out and "hdr-gs" in out


class TestReadsWhatItWrote:
    def test_detected_and_equal_to_the_studio_scene(self, written, tiny_demo, monkeypatch):
        from mono_hdr_plugin.apps.studio import scenes

        assert detect_layout(written) == "scene-json"
        monkeypatch.setitem(scenes.SCENES, "demo", tiny_demo)
        original = load_scene(DataConfig(scene="demo", protocol="multi"))
        loaded = load_scene(DataConfig(data=written, protocol="multi"))
        assert len(loaded.train) == len(original.train) and len(loaded.test) == len(original.test)
        for a, b in zip(original.train + original.test, loaded.train + loaded.test):
            torch.testing.assert_close(b.camera.c2w, a.camera.c2w)
            assert (b.camera.fx, b.camera.near, b.camera.far) == pytest.approx(
                (a.camera.fx, a.camera.near, a.camera.far)
            )
            assert a.exposure == b.exposure and torch.equal(a.image, b.image) and torch.equal(a.hdr, b.hdr)

    def test_trains_two_steps(self, written, tmp_path):
        scene = load_scene(DataConfig(data=written))
        config = train_config_for(register_backbone.VoxelGridConfig)(
            backbone=register_backbone.VoxelGridConfig(resolution=8, samples_per_ray=8),
            out=tmp_path / "run",
            quiet=True,
            max_steps=2,
            save_renders=False,
        )
        records = [Trainer(config, "voxel-grid", scene).train_step() for _ in range(2)]
        assert all(math.isfinite(r["loss"]) for r in records)

    def test_broken_index_names_the_file(self, written):
        index = json.loads((written / "scene.json").read_text())
        del index["views"][0]["fx"]
        (written / "scene.json").write_text(json.dumps(index))
        with pytest.raises(DatasetError, match=r"scene\.json: KeyError: 'fx'"):
            load_scene(DataConfig(data=written))
