"""The NeRF grid-field kernels (multi-resolution encoding, occupancy marching), built on first use."""

from pathlib import Path
from typing import Any

from mono_hdr_plugin.core.cpp_extensions import load_cpp_extension

SOURCE = Path(__file__).parent / "csrc" / "nerf_kernels.cpp"


def load_extension() -> Any:
    return load_cpp_extension("nerf_kernels", SOURCE)
