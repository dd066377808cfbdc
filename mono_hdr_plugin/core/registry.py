"""Plugin registries: backbones, methods, dataset layouts, scene sources and benchmarks all work one way.

Register in Python with a decorator (`@register_backbone("name")`, `@register_method(...)`,
`@register_layout(...)`, `@register_benchmark(...)`), or from an installed package through an
entry-point group (`mono_hdr.backbones`, `mono_hdr.methods`, `mono_hdr.layouts`,
`mono_hdr.scene_sources`, `mono_hdr.benchmarks`). A plugin that fails to import is reported by
name with its exception; the others keep working. The built-in nerf and gs backbones, the 3DGS
rasteriser benchmark and the studio's scenes come through entry points, so `mono_hdr_plugin`
imports neither.
"""

import dataclasses
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from mono_hdr_plugin.core.backbone import Backbone

Plugin = TypeVar("Plugin")


class RegistryError(RuntimeError):
    """A plugin name clashes, or a requested plugin is missing, broken or of the wrong kind."""


@dataclass(frozen=True)
class PluginEntry(Generic[Plugin]):
    name: str
    plugin: Plugin
    source: str  # "python: module" or "entry point: module:attr (distribution)"


class PluginRegistry(Generic[Plugin]):
    """Named plugins of one kind, from decorators and from one entry-point group.

    `validate(name, plugin)` raises RegistryError when `plugin` is not of this kind.
    """

    def __init__(self, kind: str, entry_point_group: str, validate: Callable[[str, Any], None]):
        self.kind, self.entry_point_group, self._validate = kind, entry_point_group, validate
        self._entries: dict[str, PluginEntry[Plugin]] = {}
        self._broken: dict[str, str] = {}
        self._entry_points_loaded = False

    def register(self, name: str, source: str | None = None) -> Callable[[Plugin], Plugin]:
        """Decorator: make `plugin` available under `name`."""

        def decorator(plugin: Plugin) -> Plugin:
            self._validate(name, plugin)
            existing = self._entries.get(name)
            if existing is not None and existing.plugin is not plugin:
                label = getattr(plugin, "__qualname__", repr(plugin))
                raise RegistryError(
                    f"{self.kind} name {name!r} is already registered by {existing.source}; "
                    f"pick another name for {getattr(plugin, '__module__', '?')}.{label}"
                )
            self._entries[name] = PluginEntry(name, plugin, source or f"python: {getattr(plugin, '__module__', '?')}")
            return plugin

        return decorator

    def _load_entry_points(self) -> None:
        if self._entry_points_loaded:
            return
        self._entry_points_loaded = True
        for entry_point in entry_points(group=self.entry_point_group):
            distribution = entry_point.dist.name if entry_point.dist is not None else "unknown"
            source = f"entry point: {entry_point.value} ({distribution})"
            try:
                plugin = entry_point.load()
                if entry_point.name in self._entries and self._entries[entry_point.name].plugin is plugin:
                    continue  # the module registered itself with the decorator on import
                self.register(entry_point.name, source)(plugin)
            except Exception as error:  # noqa: BLE001 - a broken plugin must not take the others down
                message = f"{type(error).__name__}: {error}"
                self._broken[entry_point.name] = f"{source} failed to load: {message}"
                warnings.warn(
                    f"{self.kind} plugin {entry_point.name!r} ({entry_point.value}) failed to load "
                    f"and is skipped: {message}",
                    stacklevel=3,
                )

    def available(self) -> dict[str, PluginEntry[Plugin]]:
        """Every working plugin by name, in registration order (entry points load on first call)."""
        self._load_entry_points()
        return dict(self._entries)

    def broken(self) -> dict[str, str]:
        """Plugins that failed to load, with the reason."""
        self._load_entry_points()
        return dict(self._broken)

    def get(self, name: str) -> Plugin:
        """The plugin registered under `name`, or an error listing what exists."""
        available = self.available()
        if name in available:
            return available[name].plugin
        if name in self._broken:
            raise RegistryError(f"{self.kind} {name!r} is installed but broken: {self._broken[name]}")
        known = ", ".join(available) or "none"
        raise RegistryError(
            f"no {self.kind} named {name!r}; available: {known}. Register one with "
            f"the decorator or the {self.entry_point_group!r} entry-point group"
        )


def _validate_backbone(name: str, backbone_class: Any) -> None:
    if not (isinstance(backbone_class, type) and issubclass(backbone_class, Backbone)):
        raise RegistryError(
            f"backbone {name!r}: {backbone_class!r} is not a subclass of mono_hdr_plugin.core.backbone.Backbone"
        )
    if not hasattr(backbone_class, "config_class"):
        raise RegistryError(
            f"backbone {name!r}: {backbone_class.__name__} sets no `config_class` (a dataclass of its hyper-parameters)"
        )


BACKBONES: PluginRegistry[type[Backbone]] = PluginRegistry("backbone", "mono_hdr.backbones", _validate_backbone)
register_backbone = BACKBONES.register
"""Class decorator: make a Backbone subclass available as `mono-hdr train <name>`."""
get_backbone = BACKBONES.get


def _validate_benchmark(name: str, config_class: Any) -> None:
    if not (
        isinstance(config_class, type)
        and dataclasses.is_dataclass(config_class)
        and callable(getattr(config_class, "run", None))
    ):
        raise RegistryError(f"benchmark {name!r}: {config_class!r} is not a config dataclass with a `run(self)` method")
    if "out" not in {field.name for field in dataclasses.fields(config_class)}:
        raise RegistryError(
            f"benchmark {name!r}: {config_class.__name__} has no `out` field (the folder its results go to)"
        )


BENCHMARKS: PluginRegistry[type] = PluginRegistry("benchmark", "mono_hdr.benchmarks", _validate_benchmark)
register_benchmark = BENCHMARKS.register
"""Class decorator on a config dataclass with an `out: Path` field and a `run(self)` method: make it
available as `mono-hdr bench <name>` (its docstring is the help line, its fields the flags)."""
