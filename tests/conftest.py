"""Shared fixtures: the example voxel-grid backbone and its capture, a private studio cache."""

import os
import sys
from pathlib import Path

# MKL and ATen's own vectorised kernels pick their code path by CPU (AVX2, AVX-512), and paths differ
# in the last bits of a sum; over 200 training steps that grows to 1e-3 of a PSNR (MKL) and 2e-2 dB
# (ATen, the 3DGS pin on an AVX-512 machine). Pinned figures were made on the AVX2 paths, so every test
# runs on them, whatever the machine (set before torch loads; a CPU without AVX2 keeps its own).
os.environ.setdefault("MKL_CBWR", "AVX2")
os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")

import pytest
import torch
from helpers import tiny_builtin_scenes, tiny_variant

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
if str(EXAMPLES) not in sys.path:
    sys.path.insert(0, str(EXAMPLES))

torch.set_num_threads(2)


@pytest.fixture(scope="session")
def voxel_scene():
    """A 16 x 16 px HDR voxel scene photographed at one exposure (train/test alternate)."""
    import register_backbone

    return register_backbone.make_capture(size=16, views=8)


@pytest.fixture(scope="session")
def voxel_backbone_config():
    import register_backbone

    return register_backbone.VoxelGridConfig(resolution=12, samples_per_ray=24)


@pytest.fixture(scope="session")
def studio_cache(tmp_path_factory):
    """Point the render cache at a session folder, so tests never touch the user's cache."""
    folder = tmp_path_factory.mktemp("studio-cache")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MONO_HDR_CACHE", str(folder))
        yield folder


@pytest.fixture(scope="session")
def tiny_demo(studio_cache):
    """The demo scene at 24x24, 4 samples per pixel, 10 views: renders in about a second."""
    from mono_hdr_plugin.apps.studio.scenes import BUILTIN_SCENES

    return tiny_variant(next(scene for scene in BUILTIN_SCENES if scene.name == "demo"))


@pytest.fixture(autouse=True)
def tiny_scenes_outside_slow_tests(request):
    """Outside slow tests, `--scene NAME` finds tiny variants rendered into the session cache:
    the real scenes take minutes to render. Slow tests see the real ones (and the user's cache)."""
    if request.node.get_closest_marker("slow"):
        yield
        return
    request.getfixturevalue("studio_cache")
    with tiny_builtin_scenes():
        yield
