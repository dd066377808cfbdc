"""The plugin registries: one mechanism (decorator + entry points) for backbones, methods, layouts, scenes,
benchmarks."""

from dataclasses import dataclass
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from mono_hdr_plugin.core import registry
from mono_hdr_plugin.core.backbone import Backbone
from mono_hdr_plugin.core.registry import BACKBONES, BENCHMARKS, PluginRegistry, RegistryError
from mono_hdr_plugin.data.layouts import LAYOUTS
from mono_hdr_plugin.data.sources import SCENE_SOURCES
from mono_hdr_plugin.methods.base import METHODS


@dataclass
class TinyConfig:
    size: int = 1


class TinyBackbone(Backbone):
    config_class = TinyConfig


def fake_entry_points(*points):
    return lambda group: [EntryPoint(name, value, group) for name, value in points]


@pytest.fixture
def backbones(monkeypatch):
    """A fresh backbone registry with the real validation and no installed entry points."""
    fresh = PluginRegistry("backbone", "test.backbones", registry._validate_backbone)
    monkeypatch.setattr(registry, "entry_points", fake_entry_points())
    return fresh


class TestRegisterBackbone:
    def test_decorator_registers(self, backbones):
        backbones.register("tiny")(TinyBackbone)
        assert backbones.get("tiny") is TinyBackbone
        assert backbones.available()["tiny"].source.startswith("python: ")

    def test_duplicate_name_is_an_error(self, backbones):
        backbones.register("tiny")(TinyBackbone)

        class Other(TinyBackbone):
            pass

        with pytest.raises(RegistryError, match="backbone name 'tiny' is already registered"):
            backbones.register("tiny")(Other)

    def test_re_registering_same_class_is_fine(self, backbones):
        backbones.register("tiny")(TinyBackbone)
        backbones.register("tiny")(TinyBackbone)
        assert list(backbones.available()) == ["tiny"]

    def test_rejects_non_backbone(self, backbones):
        with pytest.raises(RegistryError, match="not a subclass"):
            backbones.register("x")(dict)

    def test_requires_config_class(self, backbones):
        class NoConfig(Backbone):
            pass

        with pytest.raises(RegistryError, match="config_class"):
            backbones.register("x")(NoConfig)

    def test_unknown_name_lists_available(self, backbones):
        backbones.register("tiny")(TinyBackbone)
        with pytest.raises(RegistryError, match="no backbone named 'missing'; available: tiny"):
            backbones.get("missing")

    def test_keeps_registration_order(self, backbones):
        class Second(TinyBackbone):
            pass

        backbones.register("zeta")(TinyBackbone)
        backbones.register("alpha")(Second)
        assert list(backbones.available()) == ["zeta", "alpha"]


class TestEntryPoints:
    def test_discovers_entry_point(self, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points(("tiny-ep", f"{__name__}:TinyBackbone")))
        fresh = PluginRegistry("backbone", "test.backbones", registry._validate_backbone)
        entry = fresh.available()["tiny-ep"]
        assert entry.plugin is TinyBackbone and entry.source.startswith("entry point: ")

    def test_broken_plugin_named_and_others_survive(self, monkeypatch):
        monkeypatch.setattr(
            registry,
            "entry_points",
            fake_entry_points(("broken", "no_such_module_for_mono_hdr:Thing"), ("tiny-ep", f"{__name__}:TinyBackbone")),
        )
        fresh = PluginRegistry("backbone", "test.backbones", registry._validate_backbone)
        with pytest.warns(UserWarning, match="backbone plugin 'broken'.*ModuleNotFoundError"):
            available = fresh.available()
        assert "tiny-ep" in available and "broken" not in available
        assert "ModuleNotFoundError" in fresh.broken()["broken"]
        with pytest.raises(RegistryError, match="backbone 'broken' is installed but broken"):
            fresh.get("broken")

    def test_entry_point_of_the_wrong_kind_is_reported_broken(self, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points(("odd", f"{__name__}:TinyConfig")))
        fresh = PluginRegistry("backbone", "test.backbones", registry._validate_backbone)
        with pytest.warns(UserWarning, match="'odd'.*not a subclass"):
            assert fresh.available() == {}


class TestBuiltinPlugins:
    def test_backbones_come_through_entry_points(self):
        names = {ep.name for ep in registry.entry_points(group=BACKBONES.entry_point_group)}
        assert {"nerf", "gs"} <= names
        assert BACKBONES.available()["gs"].source.startswith("entry point: backbones.gs:GaussianBackbone")

    def test_methods_layouts_and_studio(self):
        assert list(METHODS.available())[:6] == ["mono", "mlp-l2h", "mlp-h2l", "no-h2l", "hdr-nerf", "hdr-gs"]
        assert list(LAYOUTS.available())[:5] == ["llff", "hdr-gs", "hdr-nerf-synthetic", "hdr-nerf-real", "nerfstudio"]
        assert "demo" in SCENE_SOURCES.get("studio").names()

    def test_benchmarks_built_in_and_from_the_gs_entry_point(self):
        import mono_hdr_plugin.apps.bench  # noqa: F401 - registers curves and paper

        names = {ep.name for ep in registry.entry_points(group=BENCHMARKS.entry_point_group)}
        assert "raster" in names
        assert {"curves", "paper", "raster"} <= set(BENCHMARKS.available())
        assert BENCHMARKS.get("raster").__module__ == "backbones.gs.benchmark"

    @pytest.mark.parametrize(
        "kind_registry,bad", [(METHODS, dict), (LAYOUTS, dict), (SCENE_SOURCES, object()), (BENCHMARKS, dict)]
    )
    def test_each_kind_refuses_other_objects(self, kind_registry, bad):
        with pytest.raises(RegistryError, match=kind_registry.kind):
            kind_registry.register("bad")(bad)


class TestRegisterBenchmark:
    """A benchmark is its config dataclass: an `out` folder, flags as fields, `run(self)` does the work."""

    @pytest.fixture
    def benchmarks(self, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points())
        return PluginRegistry("benchmark", "test.benchmarks", registry._validate_benchmark)

    def test_config_with_run_registers(self, benchmarks):
        @dataclass
        class TinyBench:
            out: Path = Path("out")

            def run(self):
                return self.out

        benchmarks.register("tiny")(TinyBench)
        assert benchmarks.get("tiny") is TinyBench

    def test_refuses_a_class_without_run_or_out(self, benchmarks):
        @dataclass
        class NoRun:
            out: Path = Path("out")

        @dataclass
        class NoOut:
            def run(self):
                pass

        with pytest.raises(RegistryError, match="run"):
            benchmarks.register("x")(NoRun)
        with pytest.raises(RegistryError, match="no `out` field"):
            benchmarks.register("x")(NoOut)
        with pytest.raises(RegistryError, match="not a config dataclass"):
            benchmarks.register("x")(lambda: None)
