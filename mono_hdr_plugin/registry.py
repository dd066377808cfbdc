"""Backbone registry: `@register_backbone("name")` in Python, or the `mono_hdr.backbones`
entry-point group for installed plugins (the built-in nerf and gs backbones come that way).

A plugin that fails to import is reported by name with its exception; the other backbones
keep working.
"""

import warnings
from dataclasses import dataclass
from importlib.metadata import entry_points

from mono_hdr_plugin.backbone import Backbone

ENTRY_POINT_GROUP = "mono_hdr.backbones"


class BackboneRegistryError(RuntimeError):
    """A backbone name clashes, or a requested backbone is missing or broken."""


@dataclass(frozen=True)
class BackboneEntry:
    name: str
    backbone_class: type[Backbone]
    source: str  # "python: module" or "entry point: module:attr (distribution)"


_REGISTRY: dict[str, BackboneEntry] = {}
_BROKEN_PLUGINS: dict[str, str] = {}
_entry_points_loaded = False


def register_backbone(name: str, source: str | None = None):
    """Class decorator: make a Backbone subclass available as `mono-hdr train <name>`."""

    def decorator(backbone_class: type[Backbone]) -> type[Backbone]:
        if not (isinstance(backbone_class, type) and issubclass(backbone_class, Backbone)):
            raise BackboneRegistryError(f"backbone {name!r}: {backbone_class!r} is not a subclass of "
                                        "mono_hdr_plugin.backbone.Backbone")
        if not hasattr(backbone_class, "config_class"):
            raise BackboneRegistryError(f"backbone {name!r}: {backbone_class.__name__} sets no "
                                        "`config_class` (a dataclass of its hyper-parameters)")
        existing = _REGISTRY.get(name)
        if existing is not None and existing.backbone_class is not backbone_class:
            raise BackboneRegistryError(
                f"backbone name {name!r} is already registered by {existing.source}; "
                f"pick another name for {backbone_class.__module__}.{backbone_class.__qualname__}")
        _REGISTRY[name] = BackboneEntry(name, backbone_class, source or f"python: {backbone_class.__module__}")
        return backbone_class

    return decorator


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for entry_point in entry_points(group=ENTRY_POINT_GROUP):
        distribution = entry_point.dist.name if entry_point.dist is not None else "unknown"
        source = f"entry point: {entry_point.value} ({distribution})"
        try:
            backbone_class = entry_point.load()
            if entry_point.name in _REGISTRY and _REGISTRY[entry_point.name].backbone_class is backbone_class:
                continue  # the module registered itself with the decorator on import
            register_backbone(entry_point.name, source)(backbone_class)
        except Exception as error:  # a broken plugin must not take the others down
            message = f"{type(error).__name__}: {error}"
            _BROKEN_PLUGINS[entry_point.name] = f"{source} failed to load: {message}"
            warnings.warn(f"backbone plugin {entry_point.name!r} ({entry_point.value}) failed to load "
                          f"and is skipped: {message}", stacklevel=2)


def available_backbones() -> dict[str, BackboneEntry]:
    """Every working backbone by name (entry points are loaded on first call)."""
    _load_entry_points()
    return dict(sorted(_REGISTRY.items()))


def broken_plugins() -> dict[str, str]:
    """Plugins that failed to load, with the reason."""
    _load_entry_points()
    return dict(_BROKEN_PLUGINS)


def get_backbone(name: str) -> type[Backbone]:
    """The backbone class registered under `name`, or an error listing what exists."""
    backbones = available_backbones()
    if name in backbones:
        return backbones[name].backbone_class
    if name in _BROKEN_PLUGINS:
        raise BackboneRegistryError(f"backbone {name!r} is installed but broken: {_BROKEN_PLUGINS[name]}")
    known = ", ".join(backbones) or "none"
    raise BackboneRegistryError(f"no backbone named {name!r}; available: {known}. Register one with "
                                f"@register_backbone({name!r}) or the {ENTRY_POINT_GROUP!r} entry-point group")
