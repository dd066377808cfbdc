"""Dataset layouts on disk (docs/datasets.md): detect, read, write; plugins add their own.

The built-in ones are the published layouts of HDR-GS (COLMAP) and HDR-NeRF (synthetic, real), and
the real-capture layouts LLFF and nerfstudio (one photo a view, exposures learned).
Every reader returns a CapturedScene with OpenCV camera-to-world cameras; every writer takes one.
"""

from pathlib import Path

from mono_hdr_plugin.data.captures import CapturedScene
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.layouts.base import LAYOUTS, DatasetLayout, register_layout

# Imported in detection order, which sorting would change: each module registers its layout.
# llff comes first: LLFF scenes (NeRF's, Mip-NeRF 360's) also hold COLMAP's sparse/0, which hdr-gs detects,
# but their photos are not HDR-GS's <view>_<e> brackets; poses_bounds.npy is LLFF's alone.
# isort: off
from mono_hdr_plugin.data.layouts import llff  # noqa: F401 - registers the layout
from mono_hdr_plugin.data.layouts import hdr_gs  # noqa: F401 - registers the layout
from mono_hdr_plugin.data.layouts import hdr_nerf_synthetic  # noqa: F401 - registers the layout
from mono_hdr_plugin.data.layouts import hdr_nerf_real  # noqa: F401 - registers the layout
from mono_hdr_plugin.data.layouts import nerfstudio  # noqa: F401 - registers the layout
# isort: on

__all__ = [
    "LAYOUTS",
    "DatasetLayout",
    "detect_layout",
    "read_layout",
    "register_layout",
    "writable_layouts",
    "write_layout",
]


def detect_layout(folder: Path) -> str:
    """The layout of `folder`, from the files present (layouts are tried in registration order:
    the official Mono-HDR-GS code takes the COLMAP path first when sparse/ exists)."""
    layouts = LAYOUTS.available()
    for name, entry in layouts.items():
        if entry.plugin.detect(folder):
            return name
    expected = "; ".join(f"{name}: {entry.plugin.description}" for name, entry in layouts.items())
    raise DatasetError(
        f"{folder}: unknown dataset layout. Expected one of these ({expected}). Convert your "
        "photos with `mono-hdr process-data`; the layouts are described in docs/datasets.md"
    )


def read_layout(folder: str | Path, layout: str = "auto") -> CapturedScene:
    """Read a dataset folder; `layout` is a registered layout name (`mono-hdr layouts`) or "auto"."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: is a file, not a folder; pass --data the dataset folder that holds it")
    if not folder.is_dir():
        raise missing(folder, "pass --data a dataset folder")
    if layout == "auto":
        layout = detect_layout(folder)
    layouts = LAYOUTS.available()
    if layout not in layouts:
        raise DatasetError(f"unknown --layout {layout!r}; choose auto or one of {', '.join(layouts)}")
    if not layouts[layout].plugin.detect(folder):
        # The reader's own error would name a file of its layout ("run COLMAP") when the folder is another's.
        other = next((name for name, entry in layouts.items() if entry.plugin.detect(folder)), None)
        if other is not None:
            raise DatasetError(
                f"{folder} looks like layout {other}, not {layout}: pass --layout {other} (or leave --layout out)"
            )
    return layouts[layout].plugin.read(folder)


def writable_layouts() -> list[str]:
    """Registered layouts that can be written (targets of `mono-hdr synth`)."""
    return [name for name, entry in LAYOUTS.available().items() if entry.plugin.writable]


def write_layout(scene: CapturedScene, folder: str | Path, layout: str, bits: int = 8) -> None:
    """Write every photo of `scene` (and its HDR ground truth where the layout has a place for it)."""
    if layout not in writable_layouts():
        raise DatasetError(f"cannot write layout {layout!r}; choose one of {', '.join(writable_layouts())}")
    LAYOUTS.get(layout).write(scene, Path(folder), bits=bits)
