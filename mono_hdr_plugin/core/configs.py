"""Run settings as JSON and back: how a checkpoint stores the config dataclasses that built it."""

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any


def config_to_json(config: Any) -> str:
    return json.dumps(dataclasses.asdict(config), default=str)


# Field metadata key: the value a config field takes when a saved config lacks it, where that
# differs from its default; a field added with a new default behaviour needs it, so that a
# checkpoint written before the field existed renders as it was trained.
ABSENT_IN_SAVED_CONFIG = "absent_in_saved_config"
# Field metadata key of a nested config whose fields older saved configs held in the parent's own
# dict (before they moved into it): a saved config without the field rebuilds it from the parent's values.
SAVED_IN_PARENT = "saved_in_parent"


def config_from_dict(cls: type, values: dict) -> Any:
    """Rebuild a (nested) config dataclass from `dataclasses.asdict` output; a field the output
    lacks (written before the field existed) takes its ABSENT_IN_SAVED_CONFIG value, is rebuilt from
    `values` when SAVED_IN_PARENT, else takes its default."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for field in dataclasses.fields(cls):
        if field.name in values:
            kwargs[field.name] = _coerce(hints[field.name], values[field.name])
        elif field.metadata.get(SAVED_IN_PARENT) and dataclasses.is_dataclass(hints[field.name]):
            kwargs[field.name] = config_from_dict(hints[field.name], values)
        elif ABSENT_IN_SAVED_CONFIG in field.metadata:
            kwargs[field.name] = field.metadata[ABSENT_IN_SAVED_CONFIG]
    return cls(**kwargs)


def _coerce(annotation: Any, value: Any) -> Any:
    if value is None:
        return None
    if isinstance(annotation, type) and dataclasses.is_dataclass(annotation):
        return config_from_dict(annotation, value)
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        options = [option for option in typing.get_args(annotation) if option is not type(None)]
        if isinstance(value, dict):  # a union of config dataclasses: the one that has every field the values name
            for option in options:
                config = typing.get_args(option)[0] if typing.get_origin(option) is typing.Annotated else option
                if (
                    isinstance(config, type)
                    and dataclasses.is_dataclass(config)
                    and set(value) <= {f.name for f in dataclasses.fields(config)}
                ):
                    return config_from_dict(config, value)
        return _coerce(options[0], value)
    if origin is typing.Annotated:
        return _coerce(typing.get_args(annotation)[0], value)
    if annotation is Path:
        return Path(value)
    if origin is tuple:
        return tuple(value)
    return value
