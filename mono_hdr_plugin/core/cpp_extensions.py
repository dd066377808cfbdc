"""Builds a backbone's C++/OpenMP kernels on first use and caches them.

Built at first use rather than at install time: an isolated pip build environment would pull a
multi-GB CUDA torch. The build goes to $TORCH_EXTENSIONS_DIR when set, else to
~/.cache/mono-hdr-3d/torch_extensions; torch rebuilds it when the source or the flags change.
"""

import functools
import os
import sys
from pathlib import Path
from types import ModuleType

import torch


def vector_flags() -> tuple[str, list[str]]:
    """Name suffix and flags for the widest vector unit this CPU and torch agree on.

    Not -march=native: a shared cache directory could be reused on another CPU.
    """
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        return "avx2", ["-mavx2", "-mfma"]
    return "generic", []


@functools.cache
def load_cpp_extension(name: str, source: Path) -> ModuleType:
    """The compiled module of one C++ source (compiled on the first call of a process when the
    cached build is missing or stale; a minute or so)."""
    from torch.utils.cpp_extension import load  # pulls in the compiler tool chain

    if "TORCH_EXTENSIONS_DIR" in os.environ:
        build_root = Path(os.environ["TORCH_EXTENSIONS_DIR"])
    else:
        build_root = Path.home() / ".cache" / "mono-hdr-3d" / "torch_extensions"
    suffix, flags = vector_flags()
    build_dir = build_root / f"{name}_{suffix}"
    build_dir.mkdir(parents=True, exist_ok=True)
    if not any(build_dir.glob("*.so")):  # a first build takes minutes: say so before the compiler is silent
        print(f"building the C++ kernel {name} (first use, about 1.5 minutes; cached in {build_dir})", file=sys.stderr)
    return load(
        name=f"mono_hdr_{name}_{suffix}",
        sources=[str(source)],
        extra_cflags=["-O3", "-fopenmp", *flags],
        extra_ldflags=["-fopenmp"],
        build_directory=str(build_dir),
        verbose=False,
    )
