"""The C++ rasteriser (projection, SH colours, binning, compositing), built on first use."""

from pathlib import Path
from typing import Any

from mono_hdr_plugin.core.cpp_extensions import load_cpp_extension

SOURCE = Path(__file__).parent / "csrc" / "gs_raster.cpp"


def load_extension() -> Any:
    return load_cpp_extension("gs_raster", SOURCE)
