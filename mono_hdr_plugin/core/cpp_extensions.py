"""Builds a backbone's C++/OpenMP kernels on first use and caches them.

Built at first use rather than at install time: an isolated pip build environment would pull a
multi-GB CUDA torch. The build goes to $TORCH_EXTENSIONS_DIR when set, else to
~/.cache/mono-hdr-3d/torch_extensions; torch rebuilds it when the source or the flags change.
"""

import functools
import os
import sys
import time
from pathlib import Path
from typing import Any

import torch


def vector_flags() -> tuple[str, list[str]]:
    """Name suffix and flags for the widest vector unit this CPU and torch agree on.

    Not -march=native: a shared cache directory could be reused on another CPU.
    """
    if torch.backends.cpu.get_cpu_capability() in ("AVX2", "AVX512"):
        return "avx2", ["-mavx2", "-mfma"]
    return "generic", []


STALE_LOCK_SECONDS = 900
"""A build takes a minute or two; a lock older than this was left by a build that was killed."""


def clear_stale_lock(build_dir: Path) -> None:
    """torch's build lock (build_dir/lock) is a file its holder deletes when done: a build killed
    half-way leaves it, and every later process would wait for it forever, silently. Remove it
    when it is old; say what is being waited for when it is not."""
    lock = build_dir / "lock"
    try:
        age = time.time() - lock.stat().st_mtime
    except FileNotFoundError:
        return
    if age > STALE_LOCK_SECONDS:
        lock.unlink(missing_ok=True)
        print(f"removed {lock}, left {age / 60:.0f} min ago by a kernel build that was stopped", file=sys.stderr)
    else:
        print(
            f"waiting for another process to finish building the kernels in {build_dir} (if none is running, "
            f"delete {lock})",
            file=sys.stderr,
        )


@functools.cache
def load_cpp_extension(name: str, source: Path) -> Any:
    """The operators of one C++ source, as `torch.ops.mono_hdr_<name>_<suffix>` (compiled on the
    first call of a process when the cached build is missing or stale; about 10 s).

    The sources register operators (TORCH_LIBRARY) rather than a pybind11 module: pybind11 and
    <torch/extension.h> would make each build 20-30 s longer, for nothing the kernels use.
    """
    from torch.utils.cpp_extension import load  # pulls in the compiler tool chain

    if "TORCH_EXTENSIONS_DIR" in os.environ:
        build_root = Path(os.environ["TORCH_EXTENSIONS_DIR"])
    else:
        build_root = Path.home() / ".cache" / "mono-hdr-3d" / "torch_extensions"
    suffix, flags = vector_flags()
    build_dir = build_root / f"{name}_{suffix}"
    build_dir.mkdir(parents=True, exist_ok=True)
    if not any(build_dir.glob("*.so")):  # a first build takes seconds: say so before the compiler is silent
        print(f"building the C++ kernel {name} (first use, about 10 s; cached in {build_dir})", file=sys.stderr)
    clear_stale_lock(build_dir)
    library = f"mono_hdr_{name}_{suffix}"
    load(
        name=library,
        sources=[str(source)],
        extra_cflags=["-O3", "-fopenmp", *flags],
        extra_ldflags=["-fopenmp"],
        build_directory=str(build_dir),
        is_python_module=False,
        verbose=False,
    )
    return getattr(torch.ops, library)
