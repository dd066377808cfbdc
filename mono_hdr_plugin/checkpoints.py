"""Checkpoints: written atomically, loaded with weights_only=True, versioned."""

import dataclasses
import json
import types
import typing
from pathlib import Path
from typing import Any

import torch

from mono_hdr_plugin import __version__
from mono_hdr_plugin.data.io import atomic_path

CHECKPOINT_FORMAT = "mono-hdr-3d checkpoint"
CHECKPOINT_VERSION = 2
# Why each older version cannot be read, so the refusal names what went wrong.
RETIRED_VERSIONS = {
    1: "version 1 did not save state outside the parameters (3DGS's active SH degree): its 3DGS "
       "models would load and render without view-dependent colour",
}


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable, or of another format version."""


def config_to_json(config: Any) -> str:
    return json.dumps(dataclasses.asdict(config), default=str)


def config_from_dict(cls: type, values: dict) -> Any:
    """Rebuild a (nested) config dataclass from `dataclasses.asdict` output."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for field in dataclasses.fields(cls):
        if field.name not in values:
            continue
        kwargs[field.name] = _coerce(hints[field.name], values[field.name])
    return cls(**kwargs)


def _coerce(annotation: Any, value: Any) -> Any:
    if value is None:
        return None
    if dataclasses.is_dataclass(annotation):
        return config_from_dict(annotation, value)
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        options = [option for option in typing.get_args(annotation) if option is not type(None)]
        if isinstance(value, dict):  # a union of config dataclasses: the one whose fields the values name
            for option in options:
                config = typing.get_args(option)[0] if typing.get_origin(option) is typing.Annotated else option
                if dataclasses.is_dataclass(config) and set(value) == {f.name for f in dataclasses.fields(config)}:
                    return config_from_dict(config, value)
        return _coerce(options[0], value)
    if origin is typing.Annotated:
        return _coerce(typing.get_args(annotation)[0], value)
    if annotation is Path:
        return Path(value)
    if origin is tuple:
        return tuple(value)
    return value


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """Save `payload` (state dicts, step, config JSON) with the format header, atomically."""
    payload = {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION,
               "package_version": __version__, **payload}
    with atomic_path(path) as temporary:
        torch.save(payload, temporary)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load a checkpoint safely (weights_only) and check that this version can read it."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist; pass the .pt file a training run "
                              "wrote under OUT/checkpoints/")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:
        raise CheckpointError(f"checkpoint {path} cannot be read ({type(error).__name__}: {error}); "
                              "it is truncated or not a mono-hdr-3d checkpoint") from error
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not a mono-hdr-3d checkpoint")
    version = payload.get("format_version")
    if version != CHECKPOINT_VERSION:
        reason = f" ({RETIRED_VERSIONS[version]})" if version in RETIRED_VERSIONS else ""
        raise CheckpointError(
            f"checkpoint {path} has format version {version} (written by mono-hdr-3d "
            f"{payload.get('package_version')}), this is mono-hdr-3d {__version__} which reads version "
            f"{CHECKPOINT_VERSION}{reason}: retrain, or install the version that wrote it")
    return payload
