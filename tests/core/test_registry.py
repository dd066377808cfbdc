from dataclasses import dataclass
from importlib.metadata import EntryPoint

import pytest

from mono_hdr_plugin import registry
from mono_hdr_plugin.backbone import Backbone
from mono_hdr_plugin.registry import BackboneRegistryError, register_backbone


@dataclass
class TinyConfig:
    size: int = 1


class TinyBackbone(Backbone):
    config_class = TinyConfig


@pytest.fixture
def clean_registry(monkeypatch):
    monkeypatch.setattr(registry, "_REGISTRY", {})
    monkeypatch.setattr(registry, "_BROKEN_PLUGINS", {})
    monkeypatch.setattr(registry, "_entry_points_loaded", False)


def fake_entry_points(*points):
    return lambda group: [EntryPoint(name, value, group) for name, value in points]


class TestRegisterBackbone:
    def test_decorator_registers(self, clean_registry, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points())
        register_backbone("tiny")(TinyBackbone)
        assert registry.get_backbone("tiny") is TinyBackbone
        assert registry.available_backbones()["tiny"].source.startswith("python: ")

    def test_duplicate_name_is_an_error(self, clean_registry):
        register_backbone("tiny")(TinyBackbone)

        class Other(TinyBackbone):
            pass

        with pytest.raises(BackboneRegistryError, match="'tiny' is already registered"):
            register_backbone("tiny")(Other)

    def test_re_registering_same_class_is_fine(self, clean_registry):
        register_backbone("tiny")(TinyBackbone)
        register_backbone("tiny")(TinyBackbone)

    def test_rejects_non_backbone(self, clean_registry):
        with pytest.raises(BackboneRegistryError, match="not a subclass"):
            register_backbone("x")(dict)

    def test_requires_config_class(self, clean_registry):
        class NoConfig(Backbone):
            pass

        with pytest.raises(BackboneRegistryError, match="config_class"):
            register_backbone("x")(NoConfig)

    def test_unknown_name_lists_available(self, clean_registry, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points())
        register_backbone("tiny")(TinyBackbone)
        with pytest.raises(BackboneRegistryError, match="available: tiny"):
            registry.get_backbone("missing")


class TestEntryPoints:
    def test_discovers_entry_point(self, clean_registry, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points(("tiny-ep", f"{__name__}:TinyBackbone")))
        entry = registry.available_backbones()["tiny-ep"]
        assert entry.backbone_class is TinyBackbone and entry.source.startswith("entry point: ")

    def test_broken_plugin_named_and_others_survive(self, clean_registry, monkeypatch):
        monkeypatch.setattr(registry, "entry_points", fake_entry_points(
            ("broken", "no_such_module_for_mono_hdr:Thing"), ("tiny-ep", f"{__name__}:TinyBackbone")))
        with pytest.warns(UserWarning, match="'broken'.*ModuleNotFoundError"):
            backbones = registry.available_backbones()
        assert "tiny-ep" in backbones and "broken" not in backbones
        assert "ModuleNotFoundError" in registry.broken_plugins()["broken"]
        with pytest.raises(BackboneRegistryError, match="installed but broken"):
            registry.get_backbone("broken")


def test_builtin_entry_points_are_declared():
    names = {ep.name for ep in registry.entry_points(group=registry.ENTRY_POINT_GROUP)}
    assert {"nerf", "gs"} <= names
