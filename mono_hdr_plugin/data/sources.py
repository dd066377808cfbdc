"""Named scenes made on demand (`--scene NAME`): the studio's built-in scenes, or a plugin's.

A scene source is registered like every plugin (`@register_scene_source("name")` on an
instance, or the `mono_hdr.scene_sources` entry-point group); the studio registers itself
through that group, so `mono_hdr_plugin.data` never imports it.
"""

from typing import Any

from mono_hdr_plugin.core.registry import PluginRegistry, RegistryError
from mono_hdr_plugin.data.captures import CapturedScene
from mono_hdr_plugin.data.errors import DatasetError


class SceneSource:
    """Makes the scenes it names: override `names` and `captured_scene`."""

    def names(self) -> list[str]:
        raise NotImplementedError

    def captured_scene(self, name: str, seed: int, resolution: int | None = None) -> CapturedScene:
        """Every photo of scene `name`; `seed` seeds whatever is random in the capture (sensor noise);
        `resolution`: images of that many pixels a side (None: the scene's own size)."""
        raise NotImplementedError


def _validate_source(name: str, source: Any) -> None:
    if not isinstance(source, SceneSource):
        raise RegistryError(f"scene source {name!r}: {source!r} is not a mono_hdr_plugin.data.sources.SceneSource")


SCENE_SOURCES: PluginRegistry[SceneSource] = PluginRegistry("scene source", "mono_hdr.scene_sources", _validate_source)
register_scene_source = SCENE_SOURCES.register


def scene_names() -> list[str]:
    """Every scene name any source offers."""
    return [name for entry in SCENE_SOURCES.available().values() for name in entry.plugin.names()]


def named_scene(name: str, seed: int = 0, resolution: int | None = None) -> CapturedScene:
    """The scene `name` from the source that offers it (at `resolution` x `resolution` pixels if given)."""
    for entry in SCENE_SOURCES.available().values():
        if name in entry.plugin.names():
            if resolution is None:  # a plugin source written before sizes existed takes two arguments
                return entry.plugin.captured_scene(name, seed)
            return entry.plugin.captured_scene(name, seed, resolution=resolution)
    names = scene_names()
    if not names:
        raise DatasetError(
            f"--scene {name!r}: no scene source is installed (the studio registers through the "
            "'mono_hdr.scene_sources' entry point): reinstall the package, `pip install -e .`"
        )
    raise DatasetError(
        f"unknown scene {name!r}; choose one of {', '.join(names)} (`mono-hdr scenes`), or pass --data FOLDER"
    )
