"""Builds the NeRF grid-field kernels (C++/OpenMP) on first use and caches them.

Built here rather than at install time, as the 3DGS rasteriser is: an isolated pip build
environment would pull a multi-GB CUDA torch. The build goes to $TORCH_EXTENSIONS_DIR when
set, else to ~/.cache/mono-hdr-3d/torch_extensions; torch rebuilds it when the source or the
flags change.
"""

import functools
import os
from pathlib import Path
from types import ModuleType

import torch

SOURCE = Path(__file__).parent / "csrc" / "nerf_kernels.cpp"


def _vector_flags() -> tuple[str, list[str]]:
    """Name suffix and flags for the widest vector unit this CPU and torch agree on.

    Not -march=native: a shared cache directory could be reused on another CPU.
    """
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        return "avx2", ["-mavx2", "-mfma"]
    return "generic", []


@functools.cache
def load_extension() -> ModuleType:
    """The compiled kernels (compiles on the first call of a process, ~30 s the first time)."""
    from torch.utils.cpp_extension import load  # noqa: PLC0415 - pulls in the compiler tool chain

    if "TORCH_EXTENSIONS_DIR" in os.environ:
        build_root = Path(os.environ["TORCH_EXTENSIONS_DIR"])
    else:
        build_root = Path.home() / ".cache" / "mono-hdr-3d" / "torch_extensions"
    suffix, vector_flags = _vector_flags()
    build_dir = build_root / f"nerf_kernels_{suffix}"
    build_dir.mkdir(parents=True, exist_ok=True)
    return load(
        name=f"mono_hdr_nerf_kernels_{suffix}",
        sources=[str(SOURCE)],
        extra_cflags=["-O3", "-fopenmp", *vector_flags],
        extra_ldflags=["-fopenmp"],
        build_directory=str(build_dir),
        verbose=False,
    )
