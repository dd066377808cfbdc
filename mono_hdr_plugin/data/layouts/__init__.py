"""The on-disk dataset layouts of HDR-NeRF and HDR-GS (DATASETS.md): detect, read, write.

Every reader returns a CapturedScene with OpenCV camera-to-world cameras; every writer takes one.
"""

from pathlib import Path

from mono_hdr_plugin.data.captures import CapturedScene
from mono_hdr_plugin.data.errors import DatasetError, missing
from mono_hdr_plugin.data.layouts import hdr_gs, hdr_nerf_real, hdr_nerf_synthetic

# In detection order: the official Mono-HDR-GS code takes the COLMAP path first when sparse/ exists.
LAYOUTS = {"hdr-gs": hdr_gs, "hdr-nerf-synthetic": hdr_nerf_synthetic, "hdr-nerf-real": hdr_nerf_real}


def detect_layout(folder: Path) -> str:
    """The layout of `folder`, from the files present."""
    for name, module in LAYOUTS.items():
        if module.detect(folder):
            return name
    raise DatasetError(f"{folder}: unknown dataset layout. Expected one of: sparse/0/ (hdr-gs), "
                       "transforms_train.json (hdr-nerf-synthetic), poses_bounds_exps.npy (hdr-nerf-real). "
                       "Convert your photos with `mono-hdr process-data`, or see DATASETS.md")


def read_layout(folder: str | Path, layout: str = "auto") -> CapturedScene:
    """Read a dataset folder; `layout` is one of LAYOUTS or "auto"."""
    folder = Path(folder)
    if not folder.is_dir():
        raise missing(folder, "pass --data a dataset folder")
    if layout == "auto":
        layout = detect_layout(folder)
    if layout not in LAYOUTS:
        raise DatasetError(f"unknown --layout {layout!r}; choose auto or one of {sorted(LAYOUTS)}")
    return LAYOUTS[layout].read(folder)


def write_layout(scene: CapturedScene, folder: str | Path, layout: str, bits: int = 8) -> None:
    """Write every photo of `scene` (and its HDR ground truth where the layout has a place for it)."""
    if layout not in LAYOUTS:
        raise DatasetError(f"unknown layout {layout!r}; choose one of {sorted(LAYOUTS)}")
    LAYOUTS[layout].write(scene, Path(folder), bits=bits)
