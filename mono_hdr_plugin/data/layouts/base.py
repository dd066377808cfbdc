"""What a dataset layout is, and the registry that holds them (`mono-hdr layouts`)."""

from pathlib import Path
from typing import Any, ClassVar

from mono_hdr_plugin.core.registry import PluginRegistry, RegistryError
from mono_hdr_plugin.data.captures import CapturedScene


class DatasetLayout:
    """One way of storing a dataset on disk. Subclass, set `description`, implement `detect` and
    `read` (and `write` to be a target of `mono-hdr synth` / `process-data`), then decorate
    with `@register_layout("name")` or declare it in the `mono_hdr.layouts` entry-point group.

    Readers return a CapturedScene with OpenCV camera-to-world cameras (docs/datasets.md).
    """

    description: ClassVar[str] = ""
    writable: ClassVar[bool] = False

    @staticmethod
    def detect(folder: Path) -> bool:
        """Whether `folder` looks like this layout (cheap: file names, not contents)."""
        raise NotImplementedError

    @staticmethod
    def read(folder: Path) -> CapturedScene:
        raise NotImplementedError

    @staticmethod
    def write(scene: CapturedScene, folder: Path, bits: int = 8) -> None:
        """Every photo of `scene` (and its HDR ground truth where the layout has a place for it)."""
        raise NotImplementedError


def _validate_layout(name: str, layout: Any) -> None:
    if not (isinstance(layout, type) and issubclass(layout, DatasetLayout)):
        raise RegistryError(
            f"dataset layout {name!r}: {layout!r} is not a subclass of mono_hdr_plugin.data.layouts.DatasetLayout"
        )


LAYOUTS: PluginRegistry[type[DatasetLayout]] = PluginRegistry("dataset layout", "mono_hdr.layouts", _validate_layout)
register_layout = LAYOUTS.register
